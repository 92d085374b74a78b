"""torch alone (no torchsde_lti): torch.export of torch's structured scan whose body runs a
batched matmul over two batch dims of EQUAL size fails in grad mode.

The body computes ``(x * w) @ c`` with c (B, M, n, n) and a parameter w (so the scan traces the
body through autograd). With B != M the program exports; with B == M the two dims share one
symbol s under duck sizing, matmul folds them into one of size s**2, and tracing the body's
backward raises "s**2 ... is not tracked with proxy" (torch 2.13.0, CPU). Without gradients
(``torch.no_grad()``) both export. torchsde_lti's online step met this as "s*((s**2)//s) is not
tracked with proxy" when an IMM (modes M) was exported at an example batch B = M; its step now
forms ``H P⁻ Hᵀ`` with elementwise multiply-adds (tests/nn/test_export.py,
``test_imm_with_a_batch_equal_to_its_number_of_modes_exports``).

    python experiments/export_scan_matmul.py
"""

from __future__ import annotations

import contextlib

import torch
from torch._higher_order_ops import scan

N = 2


class Cycle(torch.nn.Module):
    """A scan over xs (T, B, M, n, n) with carry c (B, M, n, n): c <- (x w) @ c."""

    def __init__(self) -> None:
        super().__init__()
        self.w = torch.nn.Parameter(torch.eye(N, dtype=torch.float64))

    def forward(self, xs: torch.Tensor) -> torch.Tensor:
        def body(c: torch.Tensor, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            out = (x * self.w) @ c
            return out.contiguous(), out.clone()

        c0 = torch.eye(N, dtype=torch.float64).expand(*xs.shape[1:3], N, N).contiguous()
        return scan(body, c0, xs)[1]


def main() -> None:
    for B, M, grad in ((3, 2, True), (3, 3, True), (3, 3, False)):
        xs = torch.randn(4, B, M, N, N, dtype=torch.float64)
        torch._dynamo.reset()
        with contextlib.nullcontext() if grad else torch.no_grad():
            try:
                torch.export.export(Cycle(), (xs,))
                outcome = "exports"
            except Exception as e:  # noqa: BLE001  (the outcome is what this script reports)
                msg = str(e)
                at = msg.find("got ")
                outcome = "FAILS: " + (msg[at + 4 : at + 80] if at >= 0 else msg[:80])
        print(f"B={B} M={M} grad={grad}: {outcome}")


if __name__ == "__main__":
    main()
