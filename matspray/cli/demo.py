"""`matspray demo`: a benchmark object, the method and its ablations, evaluation and the report."""

from pathlib import Path

from matspray.cli.options import COMPUTE_FLAGS, add_method_arguments, build_config_from_args
from matspray.cli.settings import add_set_argument


def add_parser(parser) -> None:
    parser.add_argument(
        "--out",
        type=Path,
        help="folder for the object, the run and the report (default: runs/demo-PRESET, "
        "runs/demo-PRESET-paper for --method paper)",
    )
    parser.add_argument("--shape", default="composite", help="shape of the benchmark object (default: composite)")
    parser.add_argument(
        "--object-seed", type=int, default=0, help="seed of the object's shape and materials (default 0)"
    )
    add_method_arguments(parser, visible=COMPUTE_FLAGS)
    add_set_argument(parser, "geometry.iterations=1000 refine.iterations=200")


def run(args) -> int:
    import time

    from matspray.batch.demo import run_demo

    config = build_config_from_args(args, predictor="simulated")
    refuse_paper_on_a_cpu(args.preset, config.device)
    start = time.perf_counter()
    default_out = Path("runs") / (f"demo-{args.preset}" + ("" if args.method == "matspray" else f"-{args.method}"))
    report = run_demo(
        args.out or default_out, preset=args.preset, shape=args.shape, seed=args.object_seed, config=config
    )
    print(f"demo ({config.method}) finished in {time.perf_counter() - start:.0f} s")
    print(f"tables: {report.parent / 'eval' / 'tables.md'}")
    print(f"report: {report}")
    return 0


def refuse_paper_on_a_cpu(preset: str, device: str) -> None:
    """The paper preset (a 512 px object of 100 + 200 views, 30 000 Gaussian Splatting steps) is sized for one CUDA GPU;
    on a machine without one it would run for many hours, so it runs there only when --device cpu asks for it."""
    from matspray.device import resolve_device
    from matspray.errors import SettingError

    if preset == "paper" and device == "auto" and resolve_device(device).type == "cpu":
        raise SettingError(
            "preset",
            "paper is sized for one CUDA GPU (512 px, 100 training and 200 test views, 30 000 steps) and this "
            "machine has none: many hours here. Use --preset demo, or add --device cpu to run it here anyway",
        )
