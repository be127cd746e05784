"""``host bench``: timing of the simulator, the pipeline and the runtime, and the
real-frame tables of docs/BENCHMARKS.md."""
from __future__ import annotations

import logging
from pathlib import Path

from device.errors import InputError
from host.bench import sim as bench_sim
from host.bench.runtime import bench_runtime, format_runtime
from host.bench.tables import write_tables
from host.cli.common import UserError, emit, real_data_dir, whole


log = logging.getLogger(__name__)


def _progress(message: str) -> None:
    """A benchmark's progress note (shown by default, hidden by -q)."""
    log.info("host bench: %s", message)


def cmd_bench(args):
    if args.what != "runtime":
        args.profile = args.profile or "roboskin"
    if args.what == "sim":
        res = bench_sim.bench_sim(repeats=args.repeats)
        emit(args, res, bench_sim.format_sim(res))
    elif args.what == "pipeline":
        from host.bench.specs import check_profile, check_specs
        profile = check_profile(args.profile)
        recs = check_specs([args.data])[args.data] if args.data else []
        if not args.data:
            log.info("host bench: no --data; timing simulated frames only")
        res = bench_sim.bench_pipeline(recs, repeats=max(1, min(args.repeats, 5)),
                                       profile=profile, limit=min(args.frames, 300))
        emit(args, res, bench_sim.format_pipeline(res))
    elif args.what == "runtime":
        camera = args.camera
        if camera and "://" not in camera:
            camera = f"file://{camera}"          # a bare path is a file source
        if args.imu and camera is None:
            raise UserError("--imu goes with --camera (sim://walk brings its own IMU)")
        res = bench_runtime(frames=args.frames, models=args.models, camera=camera,
                            imu=args.imu, profile=args.profile)
        emit(args, res, format_runtime(res))
    elif args.what == "tables":
        if not args.data:
            raise UserError("tables: pass --data SPEC (a CSV manifest path,label[,imu] of the "
                            "recordings; make bench writes the authors' one)")
        doc = Path(args.doc)
        if not doc.is_file():
            raise UserError(f"--doc: {doc} is not a file")
        try:
            res = write_tables(doc, args.data, frames=args.frames,
                               repeats=max(1, min(args.repeats, 5)), models=args.models,
                               progress=_progress, profile=args.profile)
        except InputError as exc:                # the document lacks the table markers
            raise UserError(f"--doc {doc}: {exc}") from None
        emit(args, res, f"wrote the real-frame tables into {doc}")
    elif args.what == "scaling":
        from host.bench.scaling import bench_scaling, format_scaling
        if args.data and not Path(args.data).is_dir():
            raise UserError(f"--data: {args.data} is not a folder (it holds roboskin/ and "
                            "tactip_shear/)")
        if args.flat_profile and not Path(args.flat_profile).is_file():
            raise UserError(f"--flat-profile: no such file: {args.flat_profile}")
        if not args.data:
            log.info("host bench: no --data; timing simulated frames only")
        res = bench_scaling(args.data, args.flat_profile, frames=min(args.frames, 400),
                            repeats=max(1, min(args.repeats, 3)), progress=_progress)
        emit(args, res, format_scaling(res))
    elif args.what == "texture-robustness":
        from host.bench.texture_robust import format_robustness, robustness
        if args.data and not Path(args.data).is_dir():
            raise UserError(f"--data: {args.data} is not a folder (it holds roboskin/)")
        res = robustness(real_data_dir(args.data), args.work, progress=_progress)
        emit(args, res, format_robustness(res))
    elif args.what == "counts":
        from host.bench import counts
        if args.data and not Path(args.data).is_dir():
            raise UserError(f"--data: {args.data} is not a folder (it holds roboskin/)")
        if args.n2 <= args.n1:
            raise UserError(f"--n1/--n2: need 1 <= n1 < n2, got n1={args.n1}, n2={args.n2}")
        if not counts.valgrind_found():
            raise UserError("counts: valgrind not found (Debian: apt-get install valgrind)")
        clips = [c for c in (args.clips or ",".join(counts.DEFAULT_CLIPS)).split(",") if c]
        res = counts.bench_counts(real_data_dir(args.data), clips, args.n1, args.n2,
                                  args.jobs, progress=_progress)
        emit(args, res, counts.format_counts(res))


def register(sub) -> None:
    """The sub-command bench."""
    s = sub.add_parser("bench", help="benchmarks (single thread, median and p99)")
    s.add_argument("what", choices=["sim", "pipeline", "runtime", "tables",
                                    "texture-robustness", "scaling", "counts"],
                   help="tables: measure on the real recordings and rewrite the "
                        "real-frame tables of --doc; texture-robustness: texture "
                        "accuracy on proxies for a new recording session; scaling: "
                        "per-frame cost against the pin count; counts: instructions "
                        "per frame with valgrind's callgrind (docs/BENCHMARKS.md)")
    s.add_argument("--data", metavar="SPEC",
                   help="pipeline, tables: the recordings, a CSV manifest (path,label[,imu]) "
                        "or a dataset folder (pipeline without it: simulated frames only); "
                        "counts: the real recordings folder (default $TACFOOT_REAL_DATA)")
    s.add_argument("--profile",
                   help="pipeline, tables: sensor profile of the recordings (name or .toml; "
                        "default roboskin); runtime: default the models' own, another is "
                        "an error")
    s.add_argument("--camera", help="runtime: a recording (path or file:// URL) "
                                    "instead of sim://walk")
    s.add_argument("--imu", help="runtime with --camera: IMU source (file://GYRO.npy "
                                 "or none; default none)")
    s.add_argument("--models", help="runtime: models folder (default: the shipped models/)")
    s.add_argument("--doc", default="docs/BENCHMARKS.md", help="tables: the document to update")
    s.add_argument("--frames", type=whole(1, 1_000_000), default=600,
                   help="frames to run (runtime, tables)")
    s.add_argument("--repeats", type=whole(1, 10_000), default=20)
    s.add_argument("--work", default="out/texture-robust",
                   help="texture-robustness: cache of the clips' features")
    s.add_argument("--flat-profile", metavar="TOML",
                   help="scaling: calibrated profile of roboskin/flatSkin.avi (host calibrate)")
    s.add_argument("--clips", help="counts: comma-separated clips in DATA/roboskin/ or "
                                   "paths (default lego_train.avi)")
    s.add_argument("--n1", type=whole(1, 100_000), default=20,
                   help="counts: the short run's frames")
    s.add_argument("--n2", type=whole(2, 100_000), default=220,
                   help="counts: the long run's frames")
    s.add_argument("--jobs", type=whole(1, 2), default=2,
                   help="counts: valgrind processes at a time")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_bench)
