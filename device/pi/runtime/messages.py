"""The packets the leg runtime sends (device.pi.protocol's messages, from
values in real units) and the commands it reads."""
from __future__ import annotations

from device.pi import protocol as P

#: what the runtime does for each COMMAND opcode
COMMAND_OPS = {P.CMD_REZERO: "rezero", P.CMD_SET_RATE: "rate",
               P.CMD_REQUEST_STATUS: "status"}
#: the CPU temperature sent when the Pi does not tell it
TEMP_UNKNOWN_C = -128
THERMAL_ZONE = "/sys/class/thermal/thermal_zone0/temp"


def cpu_temp_c() -> int:
    try:
        with open(THERMAL_ZONE) as fh:
            return int(round(int(fh.read().strip()) / 1000.0))
    except (OSError, ValueError):
        return TEMP_UNKNOWN_C


def surface_message(class_id, probs, contact, slip, slip_conf, dir_deg, mag_px, pressure,
                    pins, faults, texture_id=None) -> P.Surface:
    return P.Surface(class_id=int(class_id), probs=tuple(float(x) for x in probs),
                     contact=bool(contact), slip=bool(slip), slip_conf=float(slip_conf),
                     shear_dir_deg=float(dir_deg), shear_px=float(mag_px),
                     load_n=0.0 if pressure is None else float(pressure), pins=int(pins),
                     faults=int(faults) & 0xFFFF,
                     texture_id=P.TEXTURE_NONE if texture_id is None else int(texture_id))


def fault_message(bits, raised=0, pins_lost=0) -> P.Fault:
    return P.Fault(faults=int(bits) & 0xFFFF, raised=int(raised) & 0xFFFF,
                   pins_lost=int(pins_lost))


def heartbeat_message(uptime_s: float, fps: float, dropped: int, faults: int) -> P.Heartbeat:
    return P.Heartbeat(uptime_s=int(uptime_s), rate_fps=float(fps),
                       frames_dropped=min(int(dropped), 0xFFFF), temp_c=cpu_temp_c(),
                       faults=int(faults) & 0xFFFF)


def imu_message(mean, peak_g, samples, faults) -> P.ImuSummary:
    return P.ImuSummary(acc_mg=tuple(float(x) * 1000.0 for x in mean[:3]),
                        gyro_dps=tuple(float(x) for x in mean[3:6]),
                        acc_peak_mg=float(peak_g) * 1000.0, samples=min(int(samples), 255),
                        faults=int(faults) & 0xFFFF)


def command_op(msg) -> str:
    """What a COMMAND asks for: "rezero", "rate", "status" or "unknown"."""
    return COMMAND_OPS.get(int(msg.command), "unknown")
