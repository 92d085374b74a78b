"""Every tuning threshold of the core, in one table.

Speed thresholds choose between implementations of the SAME result (values agree to rounding);
the accuracy bounds choose where ``torch.matrix_exp`` is accurate enough to be the default's
answer. The benchmark page of the docs shows how each speed threshold is set.
"""

from __future__ import annotations

import torch

# ---- linear-algebra kernels (core/linalg.py)
#: Matrices up to this size use the unrolled Cholesky factor and triangular solves.
UNROLLED_MAX_DIM = 4
#: Batch-last products: fused multiply-adds over the contiguous batch for inner sizes up to
#: this and more than FMA_MIN_BATCH elements; one kernel (``vecdot``) or ``bmm`` otherwise.
FMA_MAX_INNER = 16
FMA_MIN_BATCH = 256

# ---- intra-op threads (core/threads.py)
#: Calls touching fewer elements than this run with one thread (the fork and join of a
#: parallel region cost more than they save).
PARALLEL_MIN_WORK = 1 << 20

# ---- argument checks (core/validation.py)
#: Up to this many values in all, the value checks (and the routing decision) run on Python
#: floats after one transfer.
PYTHON_CHECK_MAX_VALUES = 256

# ---- scaling and doubling (core/_doubling.py)
#: Sub-step bounds ‖F‖ h ≤ θ: per element (its own series on every element) and for one
#: parameter set (series terms once, so fewer doublings pay).
THETA_PER_ELEMENT = 0.25
THETA_SHARED = 1.0
#: Per-element layout: batch-last fused multiply-adds for n up to this and more than
#: BATCH_LAST_MIN_ELEMENTS elements; batch-first ``bmm`` otherwise.
BATCH_LAST_MAX_DIM = 4
BATCH_LAST_MIN_ELEMENTS = 256
#: One parameter set for at least this many elements: the shared-series specialisation.
SHARED_MIN_ELEMENTS = 32
#: Halvings of the traced (compile / export) schedule: ‖F‖ dt ≤ θ 2^32 (beyond, the result
#: is that of dt = θ 2^32 / ‖F‖, where A and Q have long converged).
TRACED_MAX_HALVINGS = 32

# ---- routing small calls to torch.matrix_exp (core/_matrix_exp.py)
#: Calls of at most this many elements are candidates.
ROUTE_MAX_ELEMENTS = 512
#: Accuracy bounds per dtype: (‖F‖_F dt, ‖C‖_F dt of the whole Van Loan block,
#: λ_min(W) / ‖W‖_F); set by tests/core/test_routing.py (Q to 1e-13 / 2e-6 against a
#: 60-digit reference, positive definite in every direction).
ROUTE_BOUNDS = {torch.float64: (1.0, 2.0, 1e-3), torch.float32: (0.5, 1.0, 1e-2)}
