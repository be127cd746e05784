"""``host deploy`` to a whole robot: every leg gets the same release, or none does.

Legs come from the command line (``host deploy pi@leg1 pi@leg2:2222 ...``) or from
a robot file (``host deploy --robot robot.toml``)::

    [[leg]]
    target = "pi@leg1"        # [USER@]HOST[:PORT]
    config = "leg1.toml"      # this leg's config, relative to robot.toml
    # optional: name, port, prefix, models, identity, camera, imu, serial (file
    # names relative to robot.toml, or absolute, or ~/...)

Options given on the command line apply to every leg; a leg's own keys win.

The order, across legs: probe every leg; build the sdist once; stage, copy and
install the release on every leg at once (each in its own folder: nothing running
changes); only when every leg has it installed, switch every leg and check each
one's health at once. If any leg fails before the switch, no leg switches (and the
new release folders are removed); if any leg fails after it, every leg that
switched goes back to the release it had, the healthy ones too. A signal
(SIGTERM, SIGHUP, SIGINT: :class:`host.deploy.ssh.Stop`) before every leg passed its
health check is such a failure on every leg at once: the same unwinding, then a
summary naming the signal.
"""
from __future__ import annotations

import base64
import binascii
import re
import tempfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path

from device.config import ConfigError, read_toml
from device.pi.models.artefact import ModelError
from device.pi.models.signature import signature_path
from host.deploy.options import DeployError, DeployInputError, DeployOptions
from host.deploy.scripts import q
from host.deploy.release import Deployer, load_key, new_release_name, summary_text
from host.deploy.signing import SigningKey, default_key_path
from host.deploy.ssh import Stop

#: keys a [[leg]] table may hold, and whether they name a file (relative to the robot file)
LEG_KEYS = {"target": False, "name": False, "port": False, "prefix": False,
            "config": True, "models": True, "identity": True, "camera": False,
            "imu": False, "serial": False}


def read_robot(path: Path | str, base: DeployOptions) -> list[DeployOptions]:
    """One DeployOptions per ``[[leg]]`` of the robot file, starting from ``base``.
    DeployInputError naming the file and the leg for anything wrong."""
    path = Path(path)
    try:
        doc = read_toml(path)
    except ConfigError as exc:
        raise DeployInputError(f"--robot: {exc}") from None
    legs = doc.get("leg") if isinstance(doc, dict) else None
    extra = sorted(set(doc) - {"leg"}) if isinstance(doc, dict) else []
    if extra:
        raise DeployInputError(f"{path}: unknown key {extra[0]!r} (a robot file holds "
                               f"[[leg]] tables)")
    if not isinstance(legs, list) or not legs or not all(isinstance(l, dict) for l in legs):
        raise DeployInputError(f"{path}: needs one [[leg]] table per leg, each with a target")
    out = []
    for i, leg in enumerate(legs, 1):
        where = f"{path}: leg {i}"
        bad = sorted(set(leg) - set(LEG_KEYS))
        if bad:
            raise DeployInputError(f"{where}: unknown key {bad[0]!r} (known: "
                                   f"{', '.join(LEG_KEYS)})")
        if "target" not in leg:
            raise DeployInputError(f"{where}: lacks target")
        kw = {}
        for k, v in leg.items():
            want, what = (int, "a whole number") if k == "port" else (str, "a string")
            if not isinstance(v, want) or isinstance(v, bool):
                raise DeployInputError(f"{where}: {k} must be {what}, got {v!r}")
            if k == "name":
                continue
            kw[k] = str(path.parent / Path(v).expanduser()) if LEG_KEYS[k] else v
        o = replace(base, **kw)
        try:
            o.check()
        except DeployInputError as exc:
            # "--camera must not ..." is about this leg's own camera key when it has one
            m = re.fullmatch(r"--([a-z-]+)(:?) (.*)", str(exc), re.S)
            if m and m[1] in leg:
                raise DeployInputError(f"{where} ({leg['target']}): {m[1]}{m[2]} {m[3]}") from None
            raise
        out.append(o)
    return out


def check_legs(legs: list[DeployOptions]) -> None:
    """Each leg's options are good and no two legs are one install."""
    if not legs:
        raise DeployInputError("no leg to deploy to")
    seen = {}
    for o in legs:
        o.check()
        where = (o.ssh_target.rpartition("@")[2], o.ssh_port or 22, o.prefix)
        if where in seen:
            raise DeployInputError(f"legs {seen[where]} and {o.target} are the same install "
                                   f"({where[0]} port {where[1]}, {o.prefix})")
        seen[where] = o.target
    if len({o.release for o in legs}) > 1:
        raise DeployInputError("every leg gets the same release name")


def _each(fn, items):
    """fn(item) for every item at once (one thread each); the results in order."""
    if len(items) == 1:
        return [fn(items[0])]
    with ThreadPoolExecutor(max_workers=len(items)) as pool:
        return list(pool.map(fn, items))


def _attempt(fn):
    """Run fn(); the DeployError it raised, or None."""
    try:
        fn()
        return None
    except DeployError as exc:
        return exc


class _Leg:
    def __init__(self, opts: DeployOptions, dry_run: bool, log, key, stop):
        tag = opts.target
        self.d = Deployer(opts, dry_run=dry_run, log=lambda m: log(f"[{tag}] {m}"), key=key)
        self.d.stop = stop
        self.res = {"target": opts.target, "prefix": opts.prefix, "ok": False,
                    "rolled_back": False}


def deploy_robot(legs: list[DeployOptions], dry_run: bool = False, log=None,
                 key=None, stop: Stop | None = None) -> dict:
    """Deploy one release to every leg, all or none (see the module doc). The
    result: ok, release, and per leg its result (steps included); ``interrupted``
    names the signal that tripped ``stop``, if one did."""
    check_legs(legs)
    log = log if log is not None else (lambda m: None)
    if key is None:
        key = load_key(legs[0], dry_run)
    for o in legs[1:]:
        load_key(replace(o, signing_key=str(key.path)) if key else o, dry_run)
    release = legs[0].release or new_release_name()
    state = [_Leg(replace(o, release=release), dry_run, log, key, stop) for o in legs]
    res = {"dry_run": dry_run, "ok": False, "release": release, "legs": [l.res for l in state],
           "rolled_back": False}
    try:
        _each(lambda l: l.d.open_connection(), state)
        errs = _each(lambda l: _attempt(lambda: l.d.begin(l.res)), state)
        if not _failed(res, state, errs, "probe"):
            with tempfile.TemporaryDirectory(prefix="tacfoot-robot-") as tmp:
                sdist = state[0].d.build_sdist(Path(tmp) / "build")
                res["sdist"] = sdist.name

                def install(pair):
                    i, l = pair
                    d = Path(tmp) / f"leg{i}"
                    d.mkdir()
                    return _attempt(lambda: l.d.install(sdist, d))

                errs = _each(install, list(enumerate(state)))
            if _failed(res, state, errs, "install"):
                _each(lambda l: l.d.discard(), state)
            else:
                _switch_all(res, state)
    except DeployError as exc:          # the build
        res["error"] = str(exc)
    finally:
        _each(lambda l: l.d.close_connection(), state)
        for l in state:
            l.res["steps"] = l.d.steps
    if stop is not None and stop.signal_name:
        res["interrupted"] = stop.signal_name
        if not res["ok"]:
            res["error"] = (f"stopped by {stop.signal_name}; " + (
                "every leg went back to the release it had" if res["rolled_back"] else
                "no leg was switched") + f" ({res.get('error')})")
    return res


def _failed(res: dict, state: list[_Leg], errs: list, phase: str) -> bool:
    bad = [(l, e) for l, e in zip(state, errs) if e is not None]
    for l, e in bad:
        l.res["error"] = str(e)
    if bad:
        res["error"] = (f"{phase} failed on {', '.join(l.d.o.target for l, _ in bad)}: "
                        f"{bad[0][1]}; no leg was switched")
    return bool(bad)


def _switch_all(res: dict, state: list[_Leg]) -> None:
    """Switch every leg and check its health; all healthy, or every leg back."""
    def switch(l):
        try:
            if l.d.switch(l.res):
                return None
            return DeployError(f"health check failed: "
                               f"{l.res['health'].get('reason', 'unknown')}")
        except DeployError as exc:
            return exc

    try:
        errs = _each(switch, state)
    except BaseException:           # Ctrl-C: never leave some legs switched
        _each(lambda l: l.d.revert(l.res, None), state)
        raise
    bad = [(l, e) for l, e in zip(state, errs) if e is not None]
    if not bad:
        _each(lambda l: l.d.commit(l.res), state)
        res["ok"] = True
        return
    for l, e in bad:
        l.res["error"] = str(e)
    _each(lambda l: l.d.revert(l.res, None), state)
    res["rolled_back"] = True
    res["error"] = (f"{', '.join(l.d.o.target for l, _ in bad)}: {bad[0][1]}; every leg "
                    f"went back to the release it had")


def _signed_by(d: Deployer, key) -> bool | None:
    """Whether the leg's current release.json carries a signature by ``key``
    (None: no key on this host to check with)."""
    if key is None:
        return None
    st = d.remote("signature", f"cd {q(d.o.prefix)}/current\n"
                  "base64 < release.json | tr -d '\\n'; echo\n"
                  "base64 < release.json.sig 2>/dev/null | tr -d '\\n'; echo\n",
                  check=False, keep_chars=1 << 22)
    parts = (st.get("stdout", "") + "\n\n").split("\n")
    with tempfile.TemporaryDirectory(prefix="tacfoot-status-") as tmp:
        f = Path(tmp) / "release.json"
        try:
            f.write_bytes(base64.b64decode(parts[0], validate=True))
            signature_path(f).write_bytes(base64.b64decode(parts[1], validate=True))
            key.verify_file(f)
            return True
        except (ValueError, binascii.Error, ModelError):
            return False


def status(legs: list[DeployOptions], wait_s: float = 5.0) -> dict:
    """Each leg's current and previous release, whether this host's key signed it,
    whether the running process belongs to the release ``current`` names and that
    release passed its health check (``.healthy``), and its health (packets flowing
    from the service within ``wait_s``). A leg that cannot be reached says so
    (``reachable`` false). ``same_release``: every leg reached runs one release;
    ``ok``: every leg reached, on one release, running it and healthy."""
    check_legs(legs)
    path = legs[0].signing_key or default_key_path()
    key = SigningKey.load(path, create=False) if Path(path).exists() else None

    def one(o):
        d = Deployer(replace(o, health_timeout_s=wait_s))
        out = {"target": o.target, "prefix": o.prefix, "reachable": False}
        try:
            d.open_connection()
            info = d.probe()
            out["reachable"] = True
            d.resolve_manager(info)
            out.update(release=info["current"].rpartition("/")[2] or None,
                       previous=info["previous"].rpartition("/")[2] or None)
            if not info["current"]:
                out["health"] = {"ok": False, "reason": "nothing deployed"}
                out["signed"] = None
                return out
            run = d.running_release()
            out["running"] = run
            out["problems"] = _release_problems(out["release"], run)
            out["health"] = d.health("health")
            out["signed"] = _signed_by(d, key)
        except DeployError as exc:
            out.update(release=None, health={"ok": False, "reason": str(exc)})
            if not out["reachable"]:
                out["error"] = str(exc)
        finally:
            d.close_connection()
        return out

    legs_out = _each(one, legs)
    reached = [l for l in legs_out if l["reachable"]]
    rels = {l["release"] for l in reached}
    same = bool(reached) and len(rels) == 1 and None not in rels
    return {"legs": legs_out, "same_release": same,
            "unreachable": [l["target"] for l in legs_out if not l["reachable"]],
            "ok": same and len(reached) == len(legs_out) and all(
                l["health"].get("ok") and not l.get("problems") for l in legs_out)}


def _release_problems(release: str | None, run: dict) -> list[str]:
    """What is wrong with what runs on a leg whose ``current`` is ``release``."""
    out = []
    if run.get("pid") is None:
        out.append("no service process runs")
    elif run.get("running") is None:
        out.append(f"cannot tell which release the running process (pid {run['pid']}) "
                   f"belongs to (started by an older host deploy: redeploy)")
    elif run["running"] != release:
        out.append(f"the running process (pid {run['pid']}) is release {run['running']}, "
                   f"not {release}, which current names")
    if not run.get("healthy"):
        out.append(f"release {release} never passed its health check")
    return out


def robot_text(res: dict) -> str:
    """One line per leg, then the verdict (a dry run: each leg's plan)."""
    if res.get("dry_run"):
        return "\n\n".join(f"# leg {l['target']}\n" + summary_text(dict(l, dry_run=True))
                           for l in res.get("legs", []))
    if "same_release" in res:
        return _status_text(res)
    lines = []
    for l in res.get("legs", []):
        h = l.get("health") or {}
        health = (f"healthy ({h.get('packets_per_s')} packets/s)" if h.get("ok") else
                  f"NOT healthy: {h.get('reason')}" if h else "")
        if res.get("ok"):
            lines.append(f"{l['target']}: release {l.get('release')} {health}".rstrip())
        elif l.get("rolled_back"):
            rb = l.get("rollback") or {}
            lines.append(f"{l['target']}: back on {rb.get('to') or 'nothing (service stopped)'}"
                         + (" (ok)" if rb.get("ok") else
                            f" (rollback FAILED: {rb.get('error') or rb.get('health')})")
                         + (f"; {l['error']}" if l.get("error") else ""))
        else:
            lines.append(f"{l['target']}: not switched, still on {l.get('previous') or 'nothing'}"
                         + (f"; {l['error']}" if l.get("error") else ""))
    if res.get("ok"):
        lines.append(f"release {res['release']} running on every leg"
                     + (f" ({res['interrupted']} came after every leg was healthy)"
                        if res.get("interrupted") else ""))
    else:
        lines.append(f"FAILED: {res.get('error')}")
    return "\n".join(lines)


def _status_text(res: dict) -> str:
    lines = []
    for l in res.get("legs", []):
        if not l.get("reachable", True):
            lines.append(f"{l['target']}: UNREACHABLE: {l.get('error')}")
            continue
        h = l.get("health") or {}
        health = (f"healthy ({h.get('packets_per_s')} packets/s)" if h.get("ok") else
                  f"NOT healthy: {h.get('reason')}")
        signed = {True: ", signed by this host", False: ", NOT signed by this host's key",
                  None: ""}[l.get("signed")]
        lines.append(f"{l['target']}: release {l.get('release')}{signed} {health}".rstrip()
                     + "".join(f"; {p}" for p in l.get("problems", [])))
    bad = res.get("unreachable") or []
    if bad:
        n = len(res["legs"]) - len(bad)
        lines.append(f"{len(bad)} of {len(res['legs'])} legs UNREACHABLE ({', '.join(bad)}); "
                     + ("no leg was reached" if n == 0 else
                        f"the {n} reached run the same release" if res["same_release"] else
                        f"the {n} reached run DIFFERENT releases"))
    else:
        lines.append("every leg runs the same release" if res["same_release"] else
                     "the legs run DIFFERENT releases")
    if not res.get("ok"):
        lines.append("NOT OK: " + ("; ".join(
            f"{l['target']}: {', '.join(l['problems'])}" for l in res["legs"]
            if l.get("problems")) or "see above"))
    return "\n".join(lines)
