"""The Foxglove layout for the leg's channels, built from code with foxglove-sdk's
``foxglove.layouts`` (the viz extra), so it cannot drift from what the runtime logs.

Two columns: the TacTip image with the pins and vectors over it above the faults
and the runtime's log lines;
then the decision timelines, the confidences, pressure and shear, the IMU and the
latency. Every topic and field a panel names is checked against the channels the
runtime writes (:func:`device.pi.runtime.mcapmsg.channels`) when the layout is
built. ``docs/foxglove-layout.json`` is this module's output (a test holds them
equal); rewrite it after a change here with::

    python -m device.pi.runtime.foxglove_layout --out docs/foxglove-layout.json

(``make layout``). Without ``--out`` it prints the layout; ``--check FILE`` exits 1
when FILE differs from it.
"""
from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

from device.errors import InputError
from device.pi.runtime.mcapmsg import channels as logged_channels

#: a message path as the panels use it: the topic, then an optional field (and index)
PATH_RE = re.compile(r"(/[A-Za-z0-9_/]+?)(?:\.(\w+)(?:\[\d+\])?)?$")

#: the panels, as plain data: (kind, title, what it shows). "series" are (message path,
#: label); the image's annotations are the topics drawn over it.
IMAGE = ("image", "TacTip: pins and vectors", {"topic": "/tacfoot/image",
                                              "annotations": ["/tacfoot/pins"]})
FAULTS = ("raw", "Faults", {"topic": "/tacfoot/faults"})
LOG = ("log", "Runtime log", {"topic": "/tacfoot/log"})
DECISIONS = ("states", "Decisions", {"series": [
    ("/tacfoot/decision.class", "surface"), ("/tacfoot/decision.texture", "texture"),
    ("/tacfoot/decision.slip", "slip"), ("/tacfoot/decision.contact", "contact")]})
PLOTS = [
    ("plot", "Decision confidence", {"series": [
        ("/tacfoot/decision.surface_conf", "surface"), ("/tacfoot/decision.slip_conf", "slip"),
        ("/tacfoot/decision.texture_conf", "texture")]}),
    ("plot", "Pressure and shear", {"series": [
        ("/tacfoot/decision.pressure", "pressure"),
        ("/tacfoot/decision.shear_mag_px", "shear px")]}),
    ("plot", "IMU acceleration (g)", {"series": [
        (f"/tacfoot/imu.acc_g[{i}]", f"a{axis}") for i, axis in enumerate("xyz")]}),
    ("plot", "Latency (ms)", {"series": [
        ("/tacfoot/latency.latency_ms", "frame to packet"),
        ("/tacfoot/latency.pipeline_ms", "frame to log")]}),
]
#: the columns, left to right, each its panels top to bottom
COLUMNS = [[IMAGE, FAULTS, LOG], [DECISIONS, *PLOTS]]


class LayoutError(InputError):
    """A panel names a topic or field the runtime does not log."""


def parse_path(path: str) -> tuple[str, str | None]:
    """A message path -> (topic, field or None): ``/tacfoot/imu.acc_g[0]`` ->
    (``/tacfoot/imu``, ``acc_g``)."""
    m = PATH_RE.fullmatch(path)
    if m is None:
        raise LayoutError(f"panel path {path!r}: not TOPIC[.FIELD[INDEX]]")
    return m.group(1), m.group(2)


def references(doc) -> list[tuple[str, str | None]]:
    """Every (topic, field) a layout document (its JSON, as a dict) names: image
    topics, annotation topics, raw message topics and each series' message path."""
    out = []
    if isinstance(doc, dict):
        for key, value in doc.items():
            if key in ("imageTopic", "topicPath", "topicToRender") and isinstance(value, str):
                out.append(parse_path(value))
            elif key == "annotations" and isinstance(value, dict):
                out.extend((topic, None) for topic in value)
            elif key == "paths" and isinstance(value, list):
                out.extend(parse_path(p["value"]) for p in value if isinstance(p, dict))
            else:
                out.extend(references(value))
    elif isinstance(doc, list):
        for item in doc:
            out.extend(references(item))
    return out


def check(doc, channels: dict | None = None) -> None:
    """LayoutError naming the first topic or field of ``doc`` not in ``channels``
    (default: the channels the runtime writes)."""
    channels = logged_channels() if channels is None else channels
    for topic, fld in references(doc):
        if topic not in channels:
            raise LayoutError(f"layout: topic {topic!r} is not a channel the runtime writes "
                              f"({', '.join(sorted(channels))})")
        props = channels[topic].get("properties")
        if fld is not None and (props is None or fld not in props):
            raise LayoutError(f"layout: {topic} has no field {fld!r} "
                              f"({', '.join(sorted(props or {}))})")


def _panel(fl, kind: str, title: str, what: dict):
    if kind == "image":
        return fl.ImagePanel(title=title, config=fl.ImageConfig(image_mode=fl.ImageModeConfig(
            image_topic=what["topic"],
            annotations={t: fl.ImageAnnotationSettings(visible=True)
                         for t in what["annotations"]})))
    if kind == "raw":
        return fl.RawMessagesPanel(title=title, config=fl.RawMessagesConfig(
            topic_path=what["topic"]))
    if kind == "log":
        return fl.LogPanel(title=title, config=fl.LogConfig(topic_to_render=what["topic"]))
    if kind == "states":
        return fl.StateTransitionsPanel(title=title, config=fl.StateTransitionsConfig(
            paths=[fl.StateTransitionsSeries(value=v, label=lab) for v, lab in what["series"]]))
    if kind == "plot":
        return fl.PlotPanel(title=title, config=fl.PlotConfig(
            paths=[fl.PlotSeries(value=v, label=lab, timestamp_method="receiveTime")
                   for v, lab in what["series"]], show_legend=True))
    raise LayoutError(f"layout: unknown panel kind {kind!r}")


def build_layout(columns=None):
    """The layout as a ``foxglove.layouts.Layout`` (needs foxglove-sdk: the viz extra)."""
    try:
        import foxglove.layouts as fl
    except ImportError as exc:
        raise LayoutError("the Foxglove layout is built with foxglove-sdk's foxglove.layouts: "
                          "pip install 'tacfoot[viz]'") from exc
    cols = COLUMNS if columns is None else columns
    return fl.Layout(content=fl.SplitContainer(direction="row", items=[
        fl.SplitItem(content=fl.SplitContainer(direction="column", items=[
            fl.SplitItem(content=_panel(fl, *p)) for p in col])) for col in cols]))


def layout_json(columns=None) -> str:
    """The layout file's text (indented, one newline at the end), checked against the
    channels."""
    doc = json.loads(build_layout(columns).to_json())
    check(doc)
    return json.dumps(doc, indent=1) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m device.pi.runtime.foxglove_layout",
                                 description="the Foxglove layout for the leg's channels")
    ap.add_argument("--out", help="write it to this file (default: print it)")
    ap.add_argument("--check", metavar="FILE",
                    help="exit 1 when FILE differs from the layout the code builds")
    args = ap.parse_args(argv)
    try:
        text = layout_json()
    except LayoutError as exc:
        print(f"foxglove_layout: error: {exc}", file=sys.stderr)
        return 2
    if args.check:
        try:
            same = Path(args.check).read_text() == text
        except OSError as exc:
            print(f"foxglove_layout: error: --check {args.check!r}: {exc.strerror}",
                  file=sys.stderr)
            return 2
        if not same:
            print(f"foxglove_layout: {args.check} differs from the layout the code builds; "
                  f"rewrite it with --out {args.check}", file=sys.stderr)
            return 1
        return 0
    if args.out:
        Path(args.out).write_text(text)
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
