"""pytest set-up shared by the test suite and the documentation's code blocks (pytest-markdown-docs)."""

import torch

# small matrices: one intra-op thread avoids contention on a shared machine (the examples in
# docs/ run several times faster than with two threads competing for busy cores)
torch.set_num_threads(1)

# docs/scripts/gen_pages.py runs at documentation build time (mkdocs-gen-files), not as a test module
collect_ignore = ["docs/scripts"]
