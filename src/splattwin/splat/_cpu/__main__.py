"""`python -m splattwin.splat._cpu --warm`: compile the CPU kernels into numba's cache now (`make venv` runs it
once after installing, so that the first `train`, `build` or test does not spend ~40 s compiling)."""

from __future__ import annotations

import argparse
import logging
import sys


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m splattwin.splat._cpu", description=__doc__)
    p.add_argument("--warm", action="store_true", required=True,
                   help="compile (or load from numba's cache) every kernel of a CPU training step")
    p.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bar or lines")
    args = p.parse_args(argv)
    from splattwin.console import StderrHandler

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s",
                        handlers=[StderrHandler()])
    from splattwin.splat._cpu import K_
    from splattwin.splat._cpu.first_run import warm

    took = warm(progress=args.progress)
    print(f"CPU kernels ready in {took:.1f} s (numba cache: {K_.raster_fwd.stats.cache_path})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
