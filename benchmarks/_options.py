"""The command line shared by the MuJoCo comparisons (throughput.py, mixed_throughput.py):
parsed before JAX is imported, since `--device` decides JAX's environment."""

import argparse
import os

CORES = os.cpu_count() or 1


def parse_options(description, add_arguments=None, argv=None, mjx=True):
    """`--quick`, `--device cpu|gpu`, `--dtype`, `--mjx` (if `mjx`: the script has an MJX
    run; else `opts.mjx` is False), plus what `add_arguments(parser)` adds; on CPU, asks
    XLA for one device per core. Call before importing JAX."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--quick", action="store_true", help="fewer sizes and steps")
    parser.add_argument("--device", choices=("cpu", "gpu"), default="cpu")
    parser.add_argument(
        "--dtype", choices=("float32", "float64"), help="default: float64 on cpu, float32 on gpu"
    )
    if mjx:
        parser.add_argument("--mjx", action="store_true", help="also run MJX on the CPU")
    else:
        parser.set_defaults(mjx=False)
    if add_arguments is not None:
        add_arguments(parser)
    opts = parser.parse_args(argv)
    if opts.mjx and opts.device == "gpu":
        parser.error("--mjx is for the CPU (on a GPU, MJX runs whenever it is installed)")
    opts.dtype = opts.dtype or ("float64" if opts.device == "cpu" else "float32")
    if opts.device == "cpu":
        os.environ.setdefault("XLA_FLAGS", f"--xla_force_host_platform_device_count={CORES}")
        os.environ.setdefault("JAX_PLATFORMS", "cpu")
    return opts


def require_device(opts) -> None:
    """Exit with a message when `--device gpu` was asked for and JAX sees no GPU (call
    after importing JAX)."""
    import jax

    if opts.device == "gpu" and jax.default_backend() != "gpu":
        raise SystemExit(f"--device gpu: JAX sees no GPU (its backend is {jax.default_backend()})")
