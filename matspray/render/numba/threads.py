"""The thread count numba's parallel loops run with, shared by every compiled kernel of backend numba (its own module
so that the kernels' modules and the backend that warms them up need not import each other)."""

from __future__ import annotations

import torch


class threads:
    """Numba's threads for the block: as many as torch's (what $MATSPRAY_THREADS sets), at most numba's pool."""

    def __enter__(self):
        import numba  # only where a kernel runs

        self.before = numba.get_num_threads()
        self.count = max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS))
        numba.set_num_threads(self.count)
        return self

    def __exit__(self, *exc):
        import numba

        numba.set_num_threads(self.before)
