"""``host scenes``, ``simulate``, ``view`` and ``demo``: the simulated sensor."""
from __future__ import annotations

import json
import math
import os
import select
import shutil
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

from device.pi import protocol as P
from device.pi.vision.pipeline import fault_names
from device.pi.models.artefact import ModelError
from device.pi.models.manifest import has_manifest, read_spec
from device.pi.runtime.load import default_models_dir
from device.sim import SURFACE_LABELS, TEXTURE_LABELS, Simulator, builtin_scenes, load_scene
from host.analysis.view import (draw_vectors, pick_frames, save_images, truth_caption,
                                truth_plot)
from host.cli.export import add_mcap_args, mcap_last_trials, open_log
from host.cli.common import (SEED, UserError, dataset_folder, emit, is_recording, number,
                             open_source, open_stream, out_file, out_folder, progress_bar,
                             whole)
from host.data.dataset import is_dataset, load_trial
from host.data.simulate import simulate_to_dataset


def cmd_scenes(args):
    rows = []
    for name in builtin_scenes():
        sc = load_scene(name)
        rows.append({"name": name, "profile": sc.profile.name, "frames":
                     int(round(sc.duration_s * sc.fps)), "duration_s": round(sc.duration_s, 3),
                     "effects": list(sc.effect_names), "description": sc.description})
    text = "\n".join(f"{r['name']:<15} {r['duration_s']:>5.2f}s  {r['description']}"
                     for r in rows)
    emit(args, rows, text)


def cmd_simulate(args):
    out = out_folder(args.out, holds=dataset_folder, what="a tacfoot dataset")
    log = None
    if args.mcap:                       # opened first: a bad FILE fails before the work
        log = open_log(args.mcap, args.mcap_image_every)
    try:
        res = simulate_to_dataset(args.scene, out, args.seed, args.trials,
                                  progress=not args.json)
        if log is not None:
            res["mcap"], log = mcap_last_trials(log, out, args.trials,
                                                 args.mcap_image_every), None
    finally:
        if log is not None:
            log.close()
    emit(args, res, f"wrote {len(res['trials'])} trial(s), {res['frames']} frames, to {args.out}"
         + (f"; {res['mcap']['file']}" if "mcap" in res else ""))


def _frames_and_truth(src: str, seed: int):
    """(frames list, truth dict | None, rest pins | None, fps) for a scene or dataset."""
    if is_dataset(src):
        tr = load_trial(src, 0)
        truth = {k: v for k, v in tr.items() if k not in ("frames", "info")}
        return tr["frames"], truth, tr.get("rest_pins_px"), float(tr["info"].get("fps", 30))
    sim = Simulator(load_scene(src), seed=seed)
    frames = [sim.render(i) for i in range(sim.n_frames)]
    return frames, sim.truth, sim.rest_pins_px, sim.fps


def cmd_view(args):
    if Path(args.out).suffix.lower() not in (".gif", ".png"):
        raise UserError(f"--out must end in .gif or .png, got {args.out!r}")
    out = out_file(args.out)
    if is_recording(args.source):
        return _view_pipeline(args)
    frames, truth, rest, fps = _frames_and_truth(args.source, args.seed)
    most = args.max_frames or (120 if out.suffix.lower() == ".gif" else 6)
    contact = np.flatnonzero(truth["contact"]) if out.suffix.lower() == ".png" else []
    if len(contact) and not args.max_frames:
        picks = contact[pick_frames(len(contact), most)]   # a contact sheet shows touches
    else:
        picks = pick_frames(len(frames), most)
    images = [draw_vectors(frames[i], rest, truth["pins_px"][i], truth["visible"][i],
                           gain=args.gain, text=truth_caption(truth, i)) for i in picks]
    save_images(images, out, fps=min(fps, 15.0))
    emit(args, {"out": str(out), "frames": [int(i) for i in picks]},
         f"wrote {out} ({len(picks)} frames)")


def _view_pipeline(args):
    """Pins and vectors found by the Pi's pipeline drawn over the frames (the
    paper's figure 3)."""
    stream = open_stream(args)
    cam = open_source(args.source)
    out = Path(args.out)
    most = args.max_frames or (120 if out.suffix.lower() == ".gif" else 6)
    total = getattr(cam, "n_frames", None) or 0
    keep = set(pick_frames(total, most).tolist()) if total else None
    images, picked = [], []
    with cam:
        for fr in cam:
            f = stream.process(fr.image, fr.t_s)
            if stream.reference is None or (keep is not None and f.index not in keep):
                continue
            if keep is None and len(images) >= most:
                break
            ref = stream.reference
            text = f"#{f.index} {'contact' if f.contact else 'no contact'} |v| {f.magnitude:.1f}px"
            if f.faults:
                text += " " + ",".join(fault_names(f.faults))
            images.append(draw_vectors(fr.image, ref, ref + f.vectors, ~f.lost, gain=args.gain,
                                       text=text))
            picked.append(f.index)
    if not images:
        raise UserError(f"{args.source}: no frame had a reference (no dome or no still start)")
    save_images(images, out, fps=15.0)
    emit(args, {"out": str(out), "frames": picked}, f"wrote {out} ({len(picked)} frames)")


def _gait_plan(scene, sim, stance_load_n: float = 8.0) -> list:
    """What a gait MCU would tell the foot for each frame of a scene: stance while
    the foot is commanded into the ground (expected load: the stance load it
    commands), the commanded drag velocity, swing otherwise."""
    plan, t_end = [], 0.0
    spans = []
    for a in scene.timeline:
        spans.append((t_end, t_end + a.duration_s, a))
        t_end += a.duration_s
    depth = sim.truth["depth_cmd_mm"]
    for i in range(sim.n_frames):
        t = i / sim.fps
        a = next((x for t0, t1, x in spans if t0 <= t < t1), spans[-1][2])
        stance = bool(depth[i] > 0)
        v = (0.0, 0.0, 0.0)
        if stance and a.kind == "drag":
            r = math.radians(a.direction_deg)
            v = (a.speed_mm_s * math.cos(r), a.speed_mm_s * math.sin(r), 0.0)
        plan.append(P.Gait(P.PHASE_STANCE if stance else P.PHASE_SWING,
                           stance_load_n if stance else 0.0, v))
    return plan


#: the simulation-trained texture model the demo uses when it is in the models folder
SIM_TEXTURE = "texture-sim"


def _read_texture_spec(folder: Path):
    """The spec of the texture model in ``folder``, None when there is none."""
    try:
        return read_spec(folder)[0] if has_manifest(folder) else None
    except (ModelError, OSError, ValueError) as exc:
        raise UserError(str(exc)) from None


def _demo_models(out: Path, models_dir: Path) -> tuple[Path, dict]:
    """(the models folder the demo's runtime loads, its texture model). With
    ``models_dir/texture-sim`` (trained on simulated floors) the runtime gets
    ``out/runtime-models``: links to every model folder of ``models_dir``, with
    texture pointing at texture-sim. Otherwise it loads ``models_dir`` itself, and
    the texture model is ``models_dir/texture`` (the real-trained one when shipped)."""
    if not models_dir.is_dir():
        raise UserError(f"--models {str(models_dir)!r}: no such models folder")
    sim_man = _read_texture_spec(models_dir / SIM_TEXTURE)
    run_dir = out / "runtime-models"
    if run_dir.is_dir():
        shutil.rmtree(run_dir)                       # a demo replaces its own files
    if sim_man is not None:
        run_dir.mkdir()
        for f in sorted(models_dir.iterdir()):
            if f.is_dir() and not f.name.startswith(".") and f.name not in ("texture",
                                                                             SIM_TEXTURE):
                (run_dir / f.name).symlink_to(f.resolve(), target_is_directory=True)
        (run_dir / "texture").symlink_to((models_dir / SIM_TEXTURE).resolve(),
                                         target_is_directory=True)
        return run_dir, {"folder": f"{models_dir.name}/{SIM_TEXTURE}", "spec": sim_man}
    spec = _read_texture_spec(models_dir / "texture")
    return models_dir, {"folder": f"{models_dir.name}/texture" if spec else None,
                        "spec": spec}


def _texture_label(texture: dict, agreement: dict) -> list[str]:
    """The lines that say which texture model the demo's texture column comes
    from: a simulation-trained model by name; a real-trained one with its figures
    on real frames (from its manifest) and its agreement on this simulated walk,
    marked out of domain."""
    spec = texture.get("spec")
    if spec is None:
        return ["texture: no texture model in the models folder (column '-')"]
    on = spec.measured.trained_on
    if on.get("data") == "simulated":
        return [f"texture: simulation-trained model ({texture['folder']})"]
    test = spec.metrics.get("test") or {}
    real = on.get("data") == "real"
    acc = on.get("real_accuracy", test.get("accuracy")) if real else test.get("accuracy")
    fig = (f"held-out accuracy {acc:.2f}" + (" on real frames" if real else "")
           + (f" (n={test['n']})" if test.get("n") else "")
           + (f", {on['split']}" if on.get("split") else "")
           if isinstance(acc, (int, float)) else "no held-out figures in its manifest")
    if real:
        lines = [f"texture: real-trained model ({texture['folder']}): {fig}"]
        where = "out of domain on this simulated walk"
    else:
        lines = [f"texture: {texture['folder']}, whose manifest does not say whether it was "
                 f"trained on real or simulated data: {fig}"]
        where = "on this simulated walk"
    if agreement.get("steps"):
        lines.append(f"  {where}: right on {agreement['steps_right']} of {agreement['steps']}"
                     f" textured steps, {agreement['frames_share']:.2f} of their contact frames")
    return lines


def _texture_agreement(rows: list) -> dict:
    """How often the texture column matches the truth on the textured steps."""
    tex = [r for r in rows if r["texture_truth"] != "-"]
    n = sum(r["contact_frames"] for r in tex)
    right = sum(r["texture_frames_right"] for r in tex)
    return {"steps": len(tex), "steps_right": sum(r["texture"] == r["texture_truth"] for r in tex),
            "frames": n, "frames_right": right, "frames_share": round(right / n, 3) if n else None}


def _annotate_packets(packets: list, out: Path, sim, classes: list) -> None:
    """Give each SURFACE packet its frame, its texture decision by name (its
    texture_id in the texture model's classes) and the simulator's true texture
    ('-' off the floor). The runtime writes one decision line per SURFACE packet,
    in order, so the k-th packet is the k-th line's frame."""
    ds = [json.loads(x) for x in (out / "decisions.jsonl").read_text().splitlines()]
    surf = [d for d in packets if d["type"] == "surface"]
    if len(surf) != len(ds):
        return                              # a lost log line: no frame to pair with
    for p, d in zip(surf, ds):
        i = int(d["index"])
        tid = p.get("texture_id", P.TEXTURE_NONE)
        p["frame"] = i
        p["texture"] = classes[tid] if tid != P.TEXTURE_NONE and tid < len(classes) else "-"
        p["texture_truth"] = _true_texture(sim, i)


def _true_texture(sim, i: int) -> str:
    """The simulator's texture under frame i; '-' off the floor or on none."""
    name = TEXTURE_LABELS[int(sim.truth["texture"][i])] if sim.truth["contact"][i] else "-"
    return "-" if name == "none" else name


def _demo_runtime(scene_name: str, seed: int, out: Path, sim, scene, realtime: bool,
                  progress: bool, models_dir: Path | None = None,
                  texture_classes: list | None = None) -> dict:
    """Run the real runtime (``python -m device.pi run``) on simulated hardware
    with its serial port on a pty; this side plays the gait MCU: it decodes every
    packet (device.pi.protocol) and answers each SURFACE with the GAIT context."""
    master, slave = os.openpty()
    slave_name = os.ttyname(slave)
    q = f"?seed={seed}" + ("&realtime=1" if realtime else "")
    cmd = [sys.executable, "-m", "device.pi", "run", "--camera", f"sim://{scene_name}{q}",
           "--imu", f"sim://{scene_name}?seed={seed}", "--serial", slave_name,
           "--json-log", str(out / "decisions.jsonl"), "--status", str(out / "status.json"),
           "--json"] + (["--models", str(models_dir)] if models_dir is not None else [])
    mcap_file = out / "run.mcap" if _has_mcap() else None      # the viz extra
    if mcap_file is not None:
        cmd += ["--mcap", str(mcap_file)]
    plan = _gait_plan(scene, sim)
    dec = P.FrameDecoder()
    packets, n_surface, seq, t0 = [], 0, 0, time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        with progress_bar(sim.n_frames, "runtime", progress) as bar:
            while True:
                r, _, _ = select.select([master], [], [], 0.05)
                data = os.read(master, 4096) if r else b""
                for raw in dec.feed(data):
                    msg = P.decode_message(raw)
                    if msg is None:
                        continue
                    d = P.message_dict(msg)
                    d.update(seq=raw.seq, t_ms=raw.t_ms,
                             host_ms=round((time.monotonic() - t0) * 1e3, 2))
                    packets.append(d)
                    if isinstance(msg, P.Surface):
                        n_surface += 1
                        bar.update(1)
                        g = plan[min(n_surface, len(plan) - 1)]
                        os.write(master, g.encode(seq, int((time.monotonic() - t0) * 1e3)))
                        seq = (seq + 1) & 0xFFFF
                if not data and proc.poll() is not None:
                    break
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
        os.close(master)
        os.close(slave)
    if proc.returncode != 0:
        raise UserError(f"the runtime failed ({proc.returncode}): {stderr.strip()[-500:]}")
    _annotate_packets(packets, out, sim, texture_classes or [])
    with open(out / "packets.jsonl", "w") as fh:
        for d in packets:
            fh.write(json.dumps(d) + "\n")
    status = json.loads(stdout.strip().splitlines()[-1])
    counts: dict = {}
    for d in packets:
        counts[d["type"]] = counts.get(d["type"], 0) + 1
    return {"command": " ".join(cmd), "packets_file": str(out / "packets.jsonl"),
            "decisions_file": str(out / "decisions.jsonl"), "packets": counts,
            "decoder": dict(dec.counters), "runtime": status,
            "mcap_file": None if mcap_file is None else str(mcap_file)}


def _has_mcap() -> bool:
    import importlib.util
    return importlib.util.find_spec("mcap") is not None


def _demo_segments(scene, sim, out: Path) -> list:
    """Per step of the scene's timeline: the true surface and what the runtime
    reported most often over the frames in contact; the texture the runtime decided
    most often over those frames beside the simulator's true texture ('-': the
    floor has none, or no contact)."""
    ds = [json.loads(x) for x in (out / "decisions.jsonl").read_text().splitlines()]
    by_index = {d["index"]: d for d in ds}
    rows, t0 = [], 0.0
    for a in scene.timeline:
        i0, i1 = int(round(t0 * sim.fps)), int(round((t0 + a.duration_s) * sim.fps))
        t0 += a.duration_s
        idx = [i for i in range(i0, min(i1, sim.n_frames))
               if sim.truth["contact"][i] and i in by_index]
        truth = Counter(SURFACE_LABELS[int(sim.truth["surface"][i])] for i in idx)
        said = Counter(by_index[i]["class"] for i in idx)
        tex_truth = Counter(_true_texture(sim, i) for i in idx)
        tex = Counter(by_index[i]["texture"] or "-" for i in idx)
        tt = tex_truth.most_common(1)[0][0] if idx else "-"
        rows.append({"t_s": round(i0 / sim.fps, 3), "action": a.kind,
                     "truth": truth.most_common(1)[0][0] if truth else "no-touch",
                     "contact_frames": len(idx),
                     "reported": said.most_common(1)[0][0] if said else "no-touch",
                     "share": round(said.most_common(1)[0][1] / len(idx), 3) if idx else None,
                     "slip_frames": sum(bool(by_index[i]["slip"]) for i in idx),
                     "texture_truth": tt,
                     "texture": tex.most_common(1)[0][0] if idx else "-",
                     "texture_frames_right": sum((by_index[i]["texture"] or "-") ==
                                                 _true_texture(sim, i) for i in idx)})
    return rows


def cmd_demo(args):
    out = out_folder(args.out, holds=lambda p: True)      # a demo replaces its own files
    out.mkdir(exist_ok=True)
    scene = load_scene(args.scene)
    sim = Simulator(scene, seed=args.seed)
    picks = pick_frames(sim.n_frames, 180)
    images = []
    with progress_bar(len(picks), f"simulating {scene.name}", not args.json) as bar:
        for i in picks:
            images.append(draw_vectors(sim.render(i), sim.rest_pins_px, sim.truth["pins_px"][i],
                                       sim.truth["visible"][i], text=truth_caption(sim.truth, i)))
            bar.update(1)
    preview = save_images(images, out / "preview.gif", fps=20)
    plot = truth_plot(sim.truth, out / "ground_truth.png",
                      title=f"scene {scene.name}, seed {args.seed}: ground truth")
    t = sim.truth
    res = {"scene": scene.name, "frames": sim.n_frames, "preview": str(preview),
           "ground_truth_plot": str(plot), "contact_frames": int(t["contact"].sum()),
           "slip_frames": int(t["slip"].sum())}
    models_dir = Path(args.models) if args.models else default_models_dir()
    run_models, texture = _demo_models(out, models_dir)
    classes = list(texture["spec"].classes) if texture["spec"] else []
    res.update(_demo_runtime(args.scene, args.seed, out, sim, scene, not args.fast,
                             not args.json, run_models, classes))
    res["segments"] = _demo_segments(scene, sim, out)
    agreement = _texture_agreement(res["segments"])
    label = _texture_label(texture, agreement)
    res["texture"] = {"model": texture["folder"], "trained_on": texture["spec"].measured.trained_on
                      if texture["spec"] else None, "agreement": agreement, "label": label}
    with open(out / "steps.jsonl", "w") as fh:
        for r in res["segments"]:
            fh.write(json.dumps(r) + "\n")
    res["steps_file"] = str(out / "steps.jsonl")
    emit(args, res, demo_text(res))


def demo_text(res: dict) -> str:
    """The demo's printout from its JSON result: the runtime's figures, the table
    of steps (surface and texture decisions beside the truth) and which texture
    model decided."""
    rt = res["runtime"]
    lines = [f"simulated {res['scene']}: {res['frames']} frames, {res['contact_frames']} in "
             f"contact, {res['slip_frames']} slipping",
             f"runtime: {' '.join(res['command'].split()[2:9])} ...",
             f"  {rt['frames']} frames, {rt['packets_sent']} packets sent "
             f"({', '.join(f'{k} {v}' for k, v in sorted(res['packets'].items()))}), "
             f"{rt['packets_dropped']} dropped, latency p50 {rt['latency_ms_p50']} ms",
             f"  {'t_s':>6} {'step':<6} {'truth':<9} {'contact':>7} {'reported':<9} "
             f"{'share':>5} {'slip':>4} {'texture':<9} {'tex-truth':<9}"]
    for r in res["segments"]:
        if r["contact_frames"]:
            lines.append(f"  {r['t_s']:>6.2f} {r['action']:<6} {r['truth']:<9} "
                         f"{r['contact_frames']:>7} {r['reported']:<9} {r['share']:>5.2f} "
                         f"{r['slip_frames']:>4} {r['texture']:<9} {r['texture_truth']:<9}")
    lines += res["texture"]["label"]
    lines += [f"steps:        {res['steps_file']}",
              f"packets:      {res['packets_file']}", f"decisions:    {res['decisions_file']}",
              f"mcap log:     {res.get('mcap_file') or 'none (pip install .[viz])'}",
              f"preview:      {res['preview']}", f"ground truth: {res['ground_truth_plot']}"]
    return "\n".join(lines)


def register(sub) -> None:
    """The sub-commands scenes, simulate, view and demo."""
    s = sub.add_parser("scenes", help="list the built-in simulator scenes")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_scenes)

    s = sub.add_parser("simulate", help="render a scene to a dataset folder")
    s.add_argument("scene", help="built-in scene name or a scene .toml file")
    s.add_argument("--out", required=True, help="dataset folder to write")
    s.add_argument("--seed", type=SEED, default=0)
    s.add_argument("--trials", type=whole(1, 10_000), default=1,
                   help="trials with seeds seed, seed+1, ...")
    add_mcap_args(s)
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_simulate)

    s = sub.add_parser("view", help="draw frames with pin vectors to a GIF or PNG")
    s.add_argument("source", help="scene name, scene .toml or dataset folder (true vectors); "
                                  "a video, image folder or sim://SCENE (the pipeline's)")
    s.add_argument("--profile", default="roboskin", help="pipeline profile (recordings)")
    s.add_argument("--out", required=True, help="preview.gif or preview.png")
    s.add_argument("--seed", type=SEED, default=0)
    s.add_argument("--max-frames", type=whole(0, 100_000), default=0,
                   help="frames to draw (default 0: 120 in a GIF, 6 in a PNG)")
    s.add_argument("--gain", type=number(0, 1000, lo_open=True), default=2.0,
                   help="arrow length per px of travel")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_view)

    s = sub.add_parser("demo", help="the main job on the simulated sensor")
    s.add_argument("--out", default="out/demo")
    s.add_argument("--scene", default="walk")
    s.add_argument("--seed", type=SEED, default=0)
    s.add_argument("--models", help="models folder (default: the package's models/); its "
                                    "texture-sim model, when there, decides the texture")
    s.add_argument("--fast", action="store_true",
                   help="do not pace the simulated camera at its frame rate (the gait "
                        "context then lags the frames)")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_demo)
