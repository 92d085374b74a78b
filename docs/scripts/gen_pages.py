"""Build-time pages (mkdocs-gen-files): the benchmark result files and the example figures.

- ``benchmarks/results/<name>.md``: every ``experiments/results/*.md`` and ``*.txt`` file, as
  measured and committed by the experiment scripts (the command that made each is in its text).
- ``examples/generated/<page>-<k>.png``: each example page's ``python`` blocks are executed
  (the same code the test suite runs), and every matplotlib figure they leave open is saved.
"""

from __future__ import annotations

import io
import re
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import mkdocs_gen_files  # noqa: E402
import torch  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "experiments" / "results"
EXAMPLES = ("recovery", "gp-equivalence", "ais-tracks", "ais-imm-smoother")  # pages whose figures are generated
FENCE = re.compile(r"^```python\n(.*?)^```", re.S | re.M)


def results_pages() -> None:
    """One page per results file, and an index of them."""
    rows = []
    for path in sorted(RESULTS.iterdir()):
        if path.suffix not in (".md", ".txt"):
            continue
        text = path.read_text(encoding="utf-8")
        if path.suffix == ".md":
            body = re.sub(r"^(#+) ", r"#\1 ", text, flags=re.M)  # the page title stays the only h1
        else:
            body = "```text\n" + text.rstrip("\n") + "\n```\n"
        with mkdocs_gen_files.open(f"benchmarks/results/{path.stem}.md", "w") as f:
            f.write(f"# {path.name}\n\n`experiments/results/{path.name}`, as committed.\n\n{body}")
        rows.append(f"| [{path.name}]({path.stem}.md) |")
    with mkdocs_gen_files.open("benchmarks/results/index.md", "w") as f:
        f.write(
            "# Result files\n\nEvery table measured by `experiments/` and committed under "
            "`experiments/results/` (JSON files are left out).\n\n| file |\n|---|\n" + "\n".join(rows) + "\n"
        )


def example_figures() -> None:
    """Run each example page's code and save the figures it draws."""
    torch.set_num_threads(1)
    for name in EXAMPLES:
        page = ROOT / "docs" / "examples" / f"{name}.md"
        start = time.perf_counter()
        for block in FENCE.findall(page.read_text(encoding="utf-8")):
            exec(compile(block, str(page), "exec"), {"__name__": "__docs__"})
        for k, num in enumerate(plt.get_fignums(), start=1):
            buf = io.BytesIO()
            plt.figure(num).savefig(buf, format="png", dpi=110)
            with mkdocs_gen_files.open(f"examples/generated/{name}-{k}.png", "wb") as f:
                f.write(buf.getvalue())
        plt.close("all")
        print(f"gen_pages: examples/{name}.md figures in {time.perf_counter() - start:.1f} s")


results_pages()
example_figures()
