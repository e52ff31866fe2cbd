"""`python -m matspray.render.numba.compile`: compile backend numba's CPU kernels now (or find them in numba's
on-disk cache), so that the first run does not wait for them. `make demo` runs it beside the byte-compilation of the
installed packages; a run compiles them itself otherwise (matspray.render.numba.backend.compile_in_background)."""

from __future__ import annotations

import sys
import time


def main() -> int:
    import numpy as np

    from matspray.render.numba.backend import ensure_compiled

    start = time.perf_counter()
    ensure_compiled(np.float32)  # says on stderr what it compiled, and in how long
    print(f"numba: the CPU kernels are ready ({time.perf_counter() - start:.1f} s)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
