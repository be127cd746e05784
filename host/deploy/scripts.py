"""What runs on the Pi: the runtime command line, the systemd unit, the
no-systemd starter ``tacfootctl`` and the health check, rendered from
:class:`host.deploy.options.DeployOptions`."""
from __future__ import annotations

import re
import shlex

from host.deploy.options import REPO, DeployOptions

UNIT_TEMPLATE = REPO / "device" / "pi" / "tacfoot.service"
SUDO = 'SUDO=; [ "$(id -u)" = 0 ] || SUDO="sudo -n"\n'


def q(s) -> str:
    return shlex.quote(str(s))


def runtime_argv(o: DeployOptions) -> list[str]:
    """The runtime command line the service runs (through PREFIX/current). Python runs
    isolated (``-I``): a PYTHONPATH or user site of the Pi's shell cannot put other code
    in front of the release's venv."""
    cur = f"{o.prefix}/current"
    argv = [f"{cur}/venv/bin/python", "-I", "-m", o.runtime_module, "run",
            "--camera", o.camera, "--imu", o.imu, "--serial", o.serial]
    if o.models_dir() is not None:
        argv += ["--models", f"{cur}/models"]
    cfg = o.config_file()
    if cfg is not None:
        argv += ["--config", f"{cur}/config/{cfg.name}"]
    argv += ["--status", status_path(o)]
    return argv + list(o.runtime_args)


def service_env(o: DeployOptions) -> list[str]:
    """The service's environment: ``--env`` and, for a named release,
    TACFOOT_RELEASE (how ``host deploy --status`` tells which release runs)."""
    return list(o.env) + ([f"TACFOOT_RELEASE={o.release}"] if o.release else [])


def status_path(o: DeployOptions) -> str:
    return f"{o.prefix}/run/status.json"


def _systemd_word(arg: str) -> str:
    """One word of a systemd command line: %, $ escaped; quoted if needed."""
    s = arg.replace("%", "%%").replace("$", "$$")
    if s and not any(c.isspace() or c in "\"'\\;" for c in s):
        return s
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"'


def render_unit(o: DeployOptions, template: str | None = None) -> str:
    """The systemd unit for these options, from device/pi/tacfoot.service."""
    text = template if template is not None else UNIT_TEMPLATE.read_text()
    user = o.service_user if o.service_user is not None else o.ssh_user
    env = "\n".join("Environment=" + _systemd_word(kv) for kv in service_env(o))
    fields = {"SERVICE": o.service_name, "PREFIX": o.prefix,
              "EXEC_START": " ".join(_systemd_word(a) for a in runtime_argv(o)),
              "USER_LINE": f"User={user}" if user and user != "root" else "",
              "ENVIRONMENT": env, "WATCHDOG_S": str(int(o.watchdog_s))}
    # one pass, so a value that itself looks like @FIELD@ is left alone
    return re.sub(r"@([A-Z_]+)@", lambda m: fields.get(m[1], m[0]), text)


def render_ctl(o: DeployOptions) -> str:
    """tacfootctl: start/stop/restart/pid with a pid file, for a Pi without
    systemd (and the tests). Same command line and environment as the unit."""
    run = f"{o.prefix}/run"
    env = "".join(f"export {kv.partition('=')[0]}={q(kv.partition('=')[2])}\n"
                  for kv in service_env(o))
    return f"""#!/bin/sh
# tacfootctl: runs the tacfoot runtime without systemd (pid file {run}/{o.service_name}.pid).
# Written by host deploy; usage: tacfootctl start|stop|restart|pid
PIDFILE={q(run + '/' + o.service_name + '.pid')}
LOG={q(run + '/' + o.service_name + '.log')}
alive() {{ kill -0 "$1" 2>/dev/null && ! grep -q '^[0-9]* ([^)]*) Z' /proc/"$1"/stat 2>/dev/null; }}
getpid() {{ p=$(cat "$PIDFILE" 2>/dev/null) || return 1; [ -n "$p" ] && alive "$p" && echo "$p"; }}
start() {{
  mkdir -p {q(run)}
  export PYTHONUNBUFFERED=1
{env}  cd {q(o.prefix)}
  nohup setsid sh -c 'echo $$ > "$0"; exec "$@"' "$PIDFILE" {shlex.join(runtime_argv(o))} \\
    </dev/null >>"$LOG" 2>&1 &
  i=0; while [ ! -s "$PIDFILE" ] && [ $i -lt 50 ]; do sleep 0.1; i=$((i+1)); done
}}
stop() {{
  p=$(getpid) || {{ rm -f "$PIDFILE"; return 0; }}
  kill -TERM "$p" 2>/dev/null
  i=0; while alive "$p" && [ $i -lt 100 ]; do sleep 0.1; i=$((i+1)); done
  alive "$p" && kill -KILL "$p" 2>/dev/null
  rm -f "$PIDFILE"
}}
case "$1" in
  start) getpid >/dev/null || {{ rm -f "$PIDFILE"; start; }} ;;
  stop) stop ;;
  restart) stop; start ;;
  pid) getpid ;;
  *) echo "usage: tacfootctl start|stop|restart|pid" >&2; exit 2 ;;
esac
"""


HEALTH_PY = r"""
import json, subprocess, sys, time
status, pid_cmd, timeout_s = sys.argv[1], sys.argv[2], float(sys.argv[3])
dead_s = float(sys.argv[4])     # give up when not active this long (0: wait it out)
marker = sys.argv[5] if len(sys.argv) > 5 else None     # written when healthy
t0 = time.monotonic()
alive_t = t0
base = None
why = "no status file"
out = {"ok": False}
while time.monotonic() - t0 < timeout_s:
    r = subprocess.run(pid_cmd, shell=True, capture_output=True, text=True)
    pid = r.stdout.strip()
    if r.returncode != 0 or not pid.isdigit() or int(pid) <= 0:
        why = "service not active"
        if dead_s > 0 and time.monotonic() - alive_t > dead_s:
            break
    else:
        alive_t = time.monotonic()
        try:
            with open(status) as fh:
                st = json.load(fh)
        except (OSError, ValueError):
            st = None
        if not isinstance(st, dict):
            why = "no status file"
        elif st.get("pid") != int(pid):
            why = "status file is not from the service process (pid %s)" % pid
        else:
            sent = st.get("packets_sent")
            if not isinstance(sent, int):
                why = "status file has no packets_sent"
            elif base is None or base[0] != pid:
                base = (pid, sent, time.monotonic())
                why = "waiting for packets_sent to grow"
            elif sent > base[1]:
                out = {"ok": True, "pid": int(pid), "packets_sent": sent,
                       "packets_per_s": round((sent - base[1]) /
                                              max(time.monotonic() - base[2], 1e-3), 1),
                       "faults": st.get("faults"), "fault_names": st.get("fault_names")}
                break
    time.sleep(0.2)
out["waited_s"] = round(time.monotonic() - t0, 2)
if out["ok"] and marker:
    try:
        with open(marker, "w") as fh:
            fh.write(json.dumps(dict(out, unix=round(time.time(), 3))) + "\n")
    except OSError as exc:
        out["marker_error"] = str(exc)
if not out["ok"]:
    out["reason"] = why
print(json.dumps(out))
sys.exit(0 if out["ok"] else 1)
"""


VERIFY_RELEASE_PY = r"""
import glob, hashlib, json, sys
from pathlib import Path
try:
    import tomllib
except ImportError:
    import tomli as tomllib
doc = json.loads(Path("release.json").read_text())
bad = []
for name, want in sorted(doc.get("files", {}).items()):
    p = Path(name)
    try:
        ok = not p.is_absolute() and ".." not in p.parts and \
            hashlib.sha256(p.read_bytes()).hexdigest() == want
    except OSError:
        ok = False
    if not ok:
        bad.append(name)
if bad:
    sys.exit("release files differ from release.json: " + ", ".join(bad[:5]))
keys = set()
for cfg in glob.glob("config/*.toml"):
    try:
        k = tomllib.loads(Path(cfg).read_text()).get("signing", {}).get("public_key", "")
    except (OSError, ValueError, AttributeError):
        continue
    if isinstance(k, str) and k.strip():
        keys.add(k.strip())
if keys:
    from device.pi.models.artefact import ModelError
    from device.pi.models.signature import decode_public_key, verify
    try:
        for k in sorted(keys):
            verify(Path("release.json").read_bytes(), Path("release.json.sig"),
                   decode_public_key(k), "release.json")
    except (ModelError, ValueError) as exc:
        sys.exit(str(exc))
print("release verified: %d files%s" % (len(doc.get("files", {})),
                                         ", signature" if keys else ""))
"""
