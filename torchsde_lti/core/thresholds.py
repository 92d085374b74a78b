"""Every tuning threshold of the core, in one table.

Speed thresholds choose between implementations of the SAME result (values agree to rounding);
the accuracy bounds (θ) set the Taylor sub-step. The benchmark page of the docs shows how each
speed threshold is set.
"""

from __future__ import annotations

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
#: Eager per-element calls whose F has at most this many entries in all (N n²) take the
#: schedule of fewest torch calls (one number of halvings for all, power series);
#: larger ones the sorted schedule (fewer flops).
FEW_ENTRIES = 2048
#: Sub-step bounds ‖F‖ h ≤ θ: few elements (power series), sorted per element (Horner series
#: on every element) and one parameter set (series terms once on n × n matrices).
THETA_PER_ELEMENT = 1.0
THETA_SORTED = 0.25
THETA_SHARED = 1.0
#: Sorted per-element layout: batch-last fused multiply-adds for n up to this and more than
#: BATCH_LAST_MIN_ELEMENTS elements; batch-first ``bmm`` otherwise.
BATCH_LAST_MAX_DIM = 4
BATCH_LAST_MIN_ELEMENTS = 256
#: One parameter set for at least this many elements: the shared-series specialisation.
SHARED_MIN_ELEMENTS = 32
#: One parameter set: the rows (ν h)^k / k! of the series by one product a row from this many
#: elements on (eagerly); fewer take one cumulative product.
ROWS_BY_PRODUCTS_MIN = 1024
#: Eager CPU calls whose (n, n) matrices take more than CHUNKED_MIN_BYTES in all run chunk by chunk,
#: a chunk CHUNK_BYTES of them: the temporaries stay small enough for the allocator to reuse
#: their memory (a fresh large allocation costs a page fault every 4 KiB) and for the caches.
CHUNKED_MIN_BYTES = 1 << 23
CHUNK_BYTES = 1 << 21
#: Halvings of the traced schedule while it records a graph (torch.compile with gradients: static
#: steps, as torch's while_loop is not differentiable): ‖F‖ dt ≤ θ 2^32 (beyond, the result is
#: that of ‖F‖ dt = θ 2^32, where A and Q of a stable F have long converged). Without a graph
#: (export, inference) the while_loop runs every halving.
TRACED_MAX_HALVINGS = 32
