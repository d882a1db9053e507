"""numpy's BLAS on one thread while fdlc computes.

Between the model's passes fdlc does many small matrix products in numpy (the registration's EM,
the assignment). numpy's OpenBLAS starts a thread per core for them, and on a two-core machine
those threads and torch's (which spin for a while after each pass) take the same cores from
each other: identification with a template took ~150 ms instead of ~50 ms in session 19
(docs/speed.md, "numpy's threads"). Holding BLAS to one thread for the length of a call removes
that; torch keeps its own threads, and the caller's BLAS setting is restored on return.
"""

from __future__ import annotations

from functools import wraps

_controller = None  # threadpoolctl's view of the loaded BLAS libraries, made on first use


def one_blas_thread(fn):
    """Run ``fn`` with numpy's BLAS limited to one thread (nested calls cost ~10 µs each)."""

    @wraps(fn)
    def limited(*args, **kwargs):
        global _controller
        if _controller is None:
            from threadpoolctl import ThreadpoolController

            _controller = ThreadpoolController()
        with _controller.limit(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return limited
