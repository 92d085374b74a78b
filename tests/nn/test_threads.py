"""No global state (DESIGN §5, issue 37 item 4): modules used from several Python threads at once.

Forward + backward from 4 threads, each with its OWN filter, failed in 19–34 of 60 calls with
"Trying to backward through the graph a second time": the modules evaluated their
parametrisations under ``torch.nn.utils.parametrize.cached()``, whose cache is one per process,
so a thread read another call's (already freed) tensors. A module shared by 4 threads in
``torch.no_grad()`` inference gives the serial results.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import torch

import torchsde_lti as tl

F64 = torch.float64
H2 = [[1.0, 0, 0, 0], [0, 0, 1.0, 0]]


def _kf() -> tl.KalmanFilter:
    sde = tl.models.integrated_ou(0.7, 0.5, dim=2, dtype=F64)
    return tl.KalmanFilter(sde, torch.tensor(H2, dtype=F64), 0.3 * torch.eye(2, dtype=F64), P0=10 * torch.eye(4, dtype=F64),
                           learn=("R", "P0"))  # fmt: skip


def _imm() -> tl.IMMFilter:
    cv = tl.models.constant_velocity(dim=2, q=0.5, dtype=F64)
    iou = tl.models.integrated_ou(1.5, 0.05, dim=2, dtype=F64)
    rates = torch.tensor([[0.0, 0.2], [0.4, 0.0]], dtype=F64)
    return tl.IMMFilter([cv, iou], torch.tensor(H2, dtype=F64), 0.4 * torch.eye(2, dtype=F64), rates)


def _data(seed: int, B: int = 4, T: int = 20) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(B, T, 2, generator=g, dtype=F64).cumsum(1), torch.rand(B, T, generator=g, dtype=F64)


def _in_threads(work: Callable[[int], object], threads: int = 4) -> tuple[list[object], list[BaseException]]:
    results: list[object] = [None] * threads
    errors: list[BaseException] = []

    def run(i: int) -> None:
        try:
            results[i] = work(i)
        except BaseException as err:  # noqa: BLE001 (collected and reported by the test)
            errors.append(err)

    pool = [threading.Thread(target=run, args=(i,)) for i in range(threads)]
    for t in pool:
        t.start()
    for t in pool:
        t.join()
    return results, errors


def test_forward_backward_from_four_threads_each_with_its_own_module():
    def work(i: int) -> list[float]:
        kf, imm = _kf(), _imm()
        losses = []
        for k in range(8):
            y, dt = _data(100 * i + k, T=10)
            loss = -kf(y, dt).log_likelihood.sum() - imm(y, dt).log_likelihood.sum()
            loss.backward()
            state, step = kf.step(kf.initial_state(4), y[:, 0], dt[:, 0])  # (the online step with gradients)
            (step.log_likelihood.sum() + state.cov.sum()).backward()
            losses.append(float(loss.detach()))
        return losses

    results, errors = _in_threads(work)
    assert not errors, [repr(e) for e in errors]
    serial = [work(i) for i in range(4)]
    assert results == serial


def test_shared_module_in_no_grad_inference_from_four_threads_gives_the_serial_results():
    kf, imm = _kf(), _imm()

    def work(i: int) -> list[torch.Tensor]:
        out = []
        with torch.no_grad():
            for k in range(3):
                y, dt = _data(10 * i + k, T=10)
                out += [kf(y, dt).log_likelihood, imm(y, dt).log_likelihood]
                state, istate = kf.initial_state(4), imm.initial_state(4)
                for t in range(4):
                    state, step = kf.step(state, y[:, t], dt[:, t])
                    istate, istep = imm.step(istate, y[:, t], dt[:, t])
                    out += [state.mean, step.log_likelihood, istate.mode_prob, istep.log_likelihood]
        return out

    results, errors = _in_threads(work)
    assert not errors, [repr(e) for e in errors]
    for i, got in enumerate(results):
        for a, b in zip(got, work(i)):  # type: ignore[arg-type]
            torch.testing.assert_close(a, b, rtol=0, atol=0)
