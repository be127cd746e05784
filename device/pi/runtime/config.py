"""The leg runtime's configuration: one TOML file (default ``device/leg.toml``).

Every key is checked by :class:`device.config.Fields`: a bad value or an unknown key
raises one :class:`device.config.ConfigError` naming the file, the dotted key and
the value, and the runtime refuses to start. Missing keys take the defaults below
(they are also what ``device/leg.toml`` spells out).

Sections and keys (units in the names)::

    [camera]   width, height (px), fps, fourcc ("MJPG" | "YUYV"), buffersize,
               stall_periods (no frame for this many periods = camera fault),
               reopen_min_s, reopen_max_s (reopen backoff, doubling)
    [imu]      summary_hz (IMU summary packets per second)
    [serial]   baudrate, stall_ms (bytes waiting and none accepted this long = link
               fault), heartbeat_hz, fault_repeat_s (FAULT repeated while a fault lasts)
    [models]   variant ("int8" | "float"), profile (pipeline profile name or .toml;
               unset: the profile the models carry, roboskin without models),
               window_T (frames in the rule fallback's window), localiser (bool: load
               and run the fixed-count localiser on every frame; off by default, as no
               decision reads its pins)
    [decision] nominal_load_n, mag_px_per_n (expected pin travel per newton of
               expected load), nominal_speed_mm_s, motion_px_per_mm (skin motion per
               mm of expected foot travel), gait_timeout_ms (older GAIT = nominal),
               gait_rule_weight (share of the gait-aware rule in the surface call
               when a learned surface model is loaded and GAIT is fresh)
    [rezero]   auto (bool), still_px, still_frames, min_interval_s; reacquire (where
               the tracker's coarse search after a jump runs: "background", beside the
               loop, the jump frame reporting every pin lost, or "inline")
    [status]   interval_s (how often --status FILE is rewritten)
    [mcap]     the ``--mcap FILE`` log (docs/viewing.md): image_every (log every Nth
               camera frame, with its pin annotations), image_width (px, the logged
               JPEG's width; the height keeps the aspect), jpeg_quality (1..100),
               vector_scale (the pin vectors drawn this many times their length),
               chunk_kb (MCAP chunk size: a crash loses at most the last chunk),
               writer ("process": a child process encodes and writes, off the
               loop's core; "thread": a thread of the runtime, for a one-core board)
    [signing]  public_key (base64 Ed25519 public key that model manifests must be
               signed with; ``host deploy`` fills it in), allow_unsigned (bool: load
               models that carry no signature; true by default, for development,
               and ``host deploy`` writes false unless the config sets it)
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

from device.config import ConfigError, Fields, read_toml
from device.pi.models.signature import decode_public_key

DEFAULT_CONFIG = Path(__file__).resolve().parents[2] / "leg.toml"


@dataclass
class CameraConfig:
    width: int = 640
    height: int = 480
    fps: float = 120.0
    fourcc: str = "MJPG"
    buffersize: int = 1
    stall_periods: float = 3.0
    reopen_min_s: float = 0.1
    reopen_max_s: float = 2.0


@dataclass
class ImuConfig:
    summary_hz: float = 20.0


@dataclass
class SerialConfig:
    baudrate: int = 921600
    stall_ms: float = 50.0
    heartbeat_hz: float = 5.0
    fault_repeat_s: float = 1.0


@dataclass
class ModelsConfig:
    variant: str = "int8"
    profile: str = "roboskin"
    window_T: int = 3
    localiser: bool = False
    #: the config names ``profile``; otherwise the runtime runs the profile the models
    #: carry (their model spec), and ``profile`` only without models
    profile_set: bool = False


@dataclass
class DecisionConfig:
    nominal_load_n: float = 8.0
    mag_px_per_n: float = 0.42
    nominal_speed_mm_s: float = 10.0
    motion_px_per_mm: float = 7.0
    gait_timeout_ms: float = 500.0
    gait_rule_weight: float = 0.5


@dataclass
class RezeroConfig:
    auto: bool = True
    still_px: float = 0.3
    still_frames: int = 10
    min_interval_s: float = 2.0
    reacquire: str = "background"


@dataclass
class StatusConfig:
    interval_s: float = 0.5


@dataclass
class McapConfig:
    image_every: int = 4
    image_width: int = 320
    jpeg_quality: int = 75
    vector_scale: float = 3.0
    chunk_kb: int = 1024
    writer: str = "process"


@dataclass
class SigningConfig:
    public_key: str = ""
    allow_unsigned: bool = True


@dataclass
class LegConfig:
    camera: CameraConfig = field(default_factory=CameraConfig)
    imu: ImuConfig = field(default_factory=ImuConfig)
    serial: SerialConfig = field(default_factory=SerialConfig)
    models: ModelsConfig = field(default_factory=ModelsConfig)
    decision: DecisionConfig = field(default_factory=DecisionConfig)
    rezero: RezeroConfig = field(default_factory=RezeroConfig)
    status: StatusConfig = field(default_factory=StatusConfig)
    source: str = ""
    signing: SigningConfig = field(default_factory=SigningConfig)
    mcap: McapConfig = field(default_factory=McapConfig)

    def to_dict(self) -> dict:
        d = asdict(self)
        d.pop("source")
        return d


def parse_leg_config(doc: dict, source: str = "") -> LegConfig:
    """A :class:`LegConfig` from a parsed TOML document; ConfigError on any bad key."""
    top = Fields(doc, "", source)
    d = LegConfig(source=source)

    c = top.sub("camera", {})
    cam = CameraConfig(
        width=c.integer("width", d.camera.width, min=8, max=8192),
        height=c.integer("height", d.camera.height, min=8, max=8192),
        fps=c.number("fps", d.camera.fps, min=1.0, max=1000.0),
        fourcc=c.string("fourcc", d.camera.fourcc, choices=("MJPG", "YUYV")),
        buffersize=c.integer("buffersize", d.camera.buffersize, min=1, max=32),
        stall_periods=c.number("stall_periods", d.camera.stall_periods, min=1.0, max=100.0),
        reopen_min_s=c.number("reopen_min_s", d.camera.reopen_min_s, min=0.0, max=60.0),
        reopen_max_s=c.number("reopen_max_s", d.camera.reopen_max_s, min=0.0, max=600.0))
    c.done()
    if cam.reopen_max_s < cam.reopen_min_s:
        c.fail("camera.reopen_max_s", cam.reopen_max_s,
               f"must be >= camera.reopen_min_s ({cam.reopen_min_s})")

    i = top.sub("imu", {})
    imu = ImuConfig(summary_hz=i.number("summary_hz", d.imu.summary_hz, min=0.1, max=1000.0))
    i.done()

    s = top.sub("serial", {})
    ser = SerialConfig(
        baudrate=s.integer("baudrate", d.serial.baudrate, min=1200, max=12_000_000),
        stall_ms=s.number("stall_ms", d.serial.stall_ms, min=1.0, max=10_000.0),
        heartbeat_hz=s.number("heartbeat_hz", d.serial.heartbeat_hz, min=0.1, max=1000.0),
        fault_repeat_s=s.number("fault_repeat_s", d.serial.fault_repeat_s, min=0.01,
                                max=3600.0))
    s.done()

    m = top.sub("models", {})
    mod = ModelsConfig(
        variant=m.string("variant", d.models.variant, choices=("int8", "float")),
        profile=m.string("profile", d.models.profile),
        window_T=m.integer("window_T", d.models.window_T, min=1, max=100),
        localiser=m.boolean("localiser", d.models.localiser),
        profile_set=m.has("profile"))
    m.done()
    if not mod.profile.strip():
        m.fail("models.profile", mod.profile, "must name a profile")

    g = top.sub("decision", {})
    dec = DecisionConfig(
        nominal_load_n=g.number("nominal_load_n", d.decision.nominal_load_n, min=0.0,
                                max=10_000.0),
        mag_px_per_n=g.number("mag_px_per_n", d.decision.mag_px_per_n, min=0.0,
                              min_exclusive=True, max=1000.0),
        nominal_speed_mm_s=g.number("nominal_speed_mm_s", d.decision.nominal_speed_mm_s,
                                    min=0.0, max=100_000.0),
        motion_px_per_mm=g.number("motion_px_per_mm", d.decision.motion_px_per_mm, min=0.0,
                                  max=1000.0),
        gait_timeout_ms=g.number("gait_timeout_ms", d.decision.gait_timeout_ms, min=1.0,
                                 max=60_000.0),
        gait_rule_weight=g.number("gait_rule_weight", d.decision.gait_rule_weight, min=0.0,
                                  max=1.0))
    g.done()

    r = top.sub("rezero", {})
    rz = RezeroConfig(
        auto=r.boolean("auto", d.rezero.auto),
        still_px=r.number("still_px", d.rezero.still_px, min=0.0, min_exclusive=True,
                          max=100.0),
        still_frames=r.integer("still_frames", d.rezero.still_frames, min=1, max=100_000),
        min_interval_s=r.number("min_interval_s", d.rezero.min_interval_s, min=0.0,
                                max=3600.0),
        reacquire=r.string("reacquire", d.rezero.reacquire, choices=("background", "inline")))
    r.done()

    st = top.sub("status", {})
    stc = StatusConfig(interval_s=st.number("interval_s", d.status.interval_s, min=0.05,
                                            max=1.0))
    st.done()

    x = top.sub("mcap", {})
    mc = McapConfig(
        image_every=x.integer("image_every", d.mcap.image_every, min=1, max=10_000),
        image_width=x.integer("image_width", d.mcap.image_width, min=16, max=8192),
        jpeg_quality=x.integer("jpeg_quality", d.mcap.jpeg_quality, min=1, max=100),
        vector_scale=x.number("vector_scale", d.mcap.vector_scale, min=0.0, max=1000.0),
        chunk_kb=x.integer("chunk_kb", d.mcap.chunk_kb, min=1, max=1_048_576),
        writer=x.string("writer", d.mcap.writer, choices=("process", "thread")))
    x.done()

    k = top.sub("signing", {})
    sig = SigningConfig(public_key=k.string("public_key", d.signing.public_key).strip(),
                        allow_unsigned=k.boolean("allow_unsigned", d.signing.allow_unsigned))
    k.done()
    if sig.public_key:
        try:
            decode_public_key(sig.public_key)
        except ValueError as exc:
            k.fail("signing.public_key", sig.public_key, str(exc))
    elif not sig.allow_unsigned:
        k.fail("signing.allow_unsigned", False, "needs signing.public_key to check "
               "signatures with")
    top.done()
    return LegConfig(cam, imu, ser, mod, dec, rz, stc, source=source, signing=sig, mcap=mc)


def load_leg_config(path: Path | str | None = None) -> LegConfig:
    """The config in ``path`` (default :data:`DEFAULT_CONFIG`). A relative
    ``models.profile`` .toml path is taken relative to the config's folder, so a
    calibrated profile travels beside its config (``host deploy`` ships both)."""
    path = Path(path) if path is not None else DEFAULT_CONFIG
    cfg = parse_leg_config(read_toml(path), source=path.name)
    prof = Path(cfg.models.profile)
    if prof.suffix == ".toml" and not prof.is_absolute():
        # a sensor profile file (from host calibrate) beside the config
        cfg = replace(cfg, models=replace(cfg.models, profile=str(path.parent / prof)))
    return cfg


__all__ = ["ConfigError", "LegConfig", "load_leg_config", "parse_leg_config",
           "DEFAULT_CONFIG"]
