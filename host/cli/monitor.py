"""``host monitor``: decode the surface link."""
from __future__ import annotations

from host.cli.common import UserError, emit, number, whole
from host.monitor import bench_link, format_bench, run_monitor


def cmd_monitor(args):
    if args.bench:
        res = bench_link()
        emit(args, res, format_bench(res))
        return
    if not args.source:
        raise UserError("give a SERIAL_URL_OR_FILE to monitor (or --bench)")
    run_monitor(args.source, as_json=args.json, count=args.count, seconds=args.seconds)


def register(sub) -> None:
    """The sub-command monitor."""
    s = sub.add_parser("monitor", help="decode surface-link packets: rate, latest state, "
                                       "drops, CRC errors")
    s.add_argument("source", nargs="?", help="serial port, pyserial URL (loop://, "
                                             "socket://host:port), pty path, or a file of "
                                             "captured bytes")
    s.add_argument("--bench", action="store_true",
                   help="time the link instead: packet size, encode/decode, MicroPython")
    s.add_argument("--count", type=whole(1), help="stop after this many messages")
    s.add_argument("--seconds", type=number(0, lo_open=True),
                   help="stop after this many seconds")
    s.add_argument("--json", action="store_true",
                   help="one JSON line per message and a summary line")
    s.set_defaults(func=cmd_monitor)
