"""``host bench``: timing of the simulator, the pipeline and the runtime."""
from __future__ import annotations

import sys

from host.bench import sim as bench_sim
from host.bench.runtime import bench_runtime, format_runtime
from host.cli.common import UserError, emit, real_data_dir, whole


def cmd_bench(args):
    if args.what == "sim":
        res = bench_sim.bench_sim(repeats=args.repeats)
        emit(args, res, bench_sim.format_sim(res))
    elif args.what == "pipeline":
        try:
            data = real_data_dir(args.data)
        except UserError:
            data = None
            print("host bench: real recordings not found; timing simulated frames only",
                  file=sys.stderr)
        res = bench_sim.bench_pipeline(data, repeats=max(1, min(args.repeats, 5)))
        emit(args, res, bench_sim.format_pipeline(res))
    elif args.what == "runtime":
        res = bench_runtime(frames=args.frames)
        emit(args, res, format_runtime(res))


def register(sub) -> None:
    """The sub-command bench."""
    s = sub.add_parser("bench", help="benchmarks (single thread, median and p99)")
    s.add_argument("what", choices=["sim", "pipeline", "runtime"])
    s.add_argument("--data", help="real recordings folder (pipeline)")
    s.add_argument("--frames", type=whole(1, 1_000_000), default=600,
                   help="frames to run (runtime)")
    s.add_argument("--repeats", type=whole(1, 10_000), default=20)
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_bench)
