"""``host deploy`` options: what to deploy where, checked before any step runs, and
the command-line arguments that fill them."""
from __future__ import annotations

import ipaddress
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

from device.config import tomllib
from device.shipped import PACKAGED, shipped
from device.shipped import models_dir as shipped_models_dir
from device.errors import TacfootError

#: the folder holding the packages: a checkout, or site-packages of an installed toolkit
REPO = Path(__file__).resolve().parents[2]
#: what the leg's source distribution is built from, beside the packages: a checkout's
#: own files, or the copies an installed wheel carries (device/shipped.py)
SOURCE_FILES = ("pyproject.toml", "setup.py", "README.md", "LICENSE", "MANIFEST.in")
MANAGERS = ("auto", "systemd", "none")


class DeployError(TacfootError):
    """A deploy step failed; the message names the step."""


class DeployInputError(TacfootError, ValueError):
    """Bad deploy options (a missing models folder, a bad --env ...)."""


#: a user name as POSIX and useradd allow it (portable characters, no leading -)
USER_RE = re.compile(r"[A-Za-z_][A-Za-z0-9._-]{0,31}")
#: one label of a host name (RFC 1123)
LABEL_RE = re.compile(r"[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?")


def _host_ok(host: str) -> bool:
    """A host name (dot-separated RFC 1123 labels, 253 characters at most) or an
    IPv4/IPv6 address."""
    try:
        ipaddress.ip_address(host)
        return True
    except ValueError:
        pass
    return 0 < len(host) <= 253 and all(LABEL_RE.fullmatch(l) for l in host.split("."))


def parse_target(target: str) -> tuple[str | None, str, int | None]:
    """(user, host, port) from ``[USER@]HOST[:PORT]`` (an IPv6 address with a port
    in brackets: ``pi@[fe80::1]:22``). DeployInputError unless the user is a POSIX
    user name, the host a host name or an IP address and the port 1..65535."""
    bad = DeployInputError(f"target must be [USER@]HOST[:PORT] with a user name and a "
                           f"host name or IP address, got {target!r}")
    if not isinstance(target, str):
        raise bad
    user, at, rest = target.rpartition("@")
    if at and not USER_RE.fullmatch(user):
        raise bad
    port = None
    if rest.startswith("["):
        host, close, tail = rest[1:].partition("]")
        if not close or (tail and not tail.startswith(":")):
            raise bad
        rest, port_s = host, tail[1:] if tail else None
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            raise bad from None
    elif rest.count(":") == 1:
        rest, _, port_s = rest.partition(":")
    else:
        port_s = None
    if port_s is not None:
        if not port_s.isdigit() or not 0 < int(port_s) < 65536:
            raise bad
        port = int(port_s)
    if not _host_ok(rest):
        raise bad
    return (user if at else None), rest, port


@dataclass
class DeployOptions:
    target: str                                  # [USER@]HOST[:PORT]
    port: int | None = None
    identity: str | None = None
    ssh_options: list[str] = field(default_factory=list)   # extra "-o" values
    prefix: str = "/opt/tacfoot"
    models: str | None = None                    # default: the repo's models/
    config: str | None = None                    # default: device/leg.toml if present
    python: str = "python3"                      # the Pi's interpreter for the venv
    service_manager: str = "auto"
    service_name: str = "tacfoot"
    service_user: str | None = None              # default: the SSH user unless root
    unit_dir: str = "/etc/systemd/system"
    system_site_packages: bool = False
    no_deps: bool = False
    camera: str = "v4l2:///dev/video0"
    imu: str = "i2c://1/0x68"
    serial: str = "/dev/serial0"
    runtime_module: str = "device.pi"
    runtime_args: list[str] = field(default_factory=list)
    env: list[str] = field(default_factory=list)         # KEY=VALUE for the service
    watchdog_s: int = 10
    health_timeout_s: float = 60.0
    keep: int = 3
    release: str | None = None
    signing_key: str | None = None               # default: host.deploy.signing's path
    allow_unsigned: bool = False                 # the shipped config's signing.allow_unsigned

    def check(self):
        _, _, tport = parse_target(self.target)
        if self.port is not None and not 0 < self.port < 65536:
            raise DeployInputError(f"--port must be 1..65535, got {self.port!r}")
        if tport is not None and self.port is not None and tport != self.port:
            raise DeployInputError(f"target {self.target!r} names port {tport}, --port "
                                   f"says {self.port}")
        if self.service_user is not None and not USER_RE.fullmatch(self.service_user):
            raise DeployInputError(f"--service-user must be a user name, got "
                                   f"{self.service_user!r}")
        if self.service_manager not in MANAGERS:
            raise DeployInputError(f"--service-manager must be one of {MANAGERS}, "
                                   f"got {self.service_manager!r}")
        if not self.prefix.startswith("/") or self.prefix.rstrip("/") in ("", "/"):
            raise DeployInputError(f"--prefix must be an absolute folder, got {self.prefix!r}")
        if not self.unit_dir.startswith("/"):
            raise DeployInputError(f"--unit-dir must be an absolute folder, got {self.unit_dir!r}")
        if not self.service_name.replace("-", "").replace("_", "").isalnum():
            raise DeployInputError(f"--service-name must be letters, digits, - or _, "
                                   f"got {self.service_name!r}")
        # these end up in the unit and in shell scripts: one line each
        for name, vals in (("prefix", [self.prefix]), ("unit-dir", [self.unit_dir]),
                           ("camera", [self.camera]), ("imu", [self.imu]),
                           ("serial", [self.serial]), ("runtime-arg", self.runtime_args),
                           ("env", self.env), ("python", [self.python]),
                           ("service-user", [self.service_user or ""]),
                           ("runtime-module", [self.runtime_module])):
            for v in vals:
                if any(ord(c) < 32 or 127 <= ord(c) < 160 or c in "\u2028\u2029" for c in v):
                    raise DeployInputError(f"--{name} must not hold control characters "
                                           f"(newline, tab...), got {v!r}")
        for name in ("camera", "imu", "serial", "python"):       # the leg's runtime would
            if not getattr(self, name).strip():                  # refuse it only after the
                raise DeployInputError(f"--{name} must not be empty, got "    # switch
                                       f"{getattr(self, name)!r}")
        for kv in self.env:
            k, eq, _ = kv.partition("=")
            if not eq or not k.replace("_", "").isalnum() or k[0].isdigit():
                raise DeployInputError(f"--env must be KEY=VALUE, got {kv!r}")
        if not self.watchdog_s >= 1:
            raise DeployInputError(f"--watchdog-s must be >= 1, got {self.watchdog_s!r}")
        if not (self.health_timeout_s > 0 and math.isfinite(self.health_timeout_s)):
            raise DeployInputError(f"--health-timeout-s must be > 0, got "
                                   f"{self.health_timeout_s!r}")
        if self.keep < 2:
            raise DeployInputError(f"--keep must be >= 2 (current and previous), got {self.keep}")
        if self.release is not None and not re.fullmatch(r"[A-Za-z0-9_+-][A-Za-z0-9._+-]*",
                                                         self.release):
            raise DeployInputError(f"--release must be letters, digits, . _ + - (a folder "
                                   f"name), got {self.release!r}")
        for name in ("models", "config"):
            p = getattr(self, name)
            if p is not None and not Path(p).exists():
                raise DeployInputError(f"--{name}: {p} not found")
        if self.models is not None and not Path(self.models).is_dir():
            raise DeployInputError(f"--models must be a folder, got {self.models!r}")
        if self.config is not None and not Path(self.config).is_file():
            raise DeployInputError(f"--config must be a file, got {self.config!r}")

    # -- derived ---------------------------------------------------------------
    @property
    def ssh_user(self) -> str | None:
        return parse_target(self.target)[0]

    @property
    def ssh_target(self) -> str:
        """USER@HOST (or HOST) as ssh takes it: the target without its port."""
        user, host, _ = parse_target(self.target)
        return f"{user}@{host}" if user else host

    @property
    def ssh_port(self) -> int | None:
        return self.port if self.port is not None else parse_target(self.target)[2]

    def models_dir(self) -> Path | None:
        if self.models:
            return Path(self.models)
        d = shipped_models_dir()        # a checkout's models/, or the wheel's copy
        return d if d.is_dir() else None

    def config_file(self) -> Path | None:
        if self.config:
            return Path(self.config)
        f = REPO / "device" / "leg.toml"
        return f if f.is_file() else None


def source_file(name: str) -> Path:
    """One of :data:`SOURCE_FILES`: the checkout's, or the installed wheel's copy."""
    return shipped(f"source/{name}")


def check_source() -> None:
    """DeployInputError (one line) when there is nothing to build the leg's source
    distribution from: neither a checkout nor a wheel that carries its source files."""
    missing = [n for n in ("pyproject.toml", "setup.py") if not source_file(n).is_file()]
    if missing:
        raise DeployInputError(
            f"host deploy builds the leg's source distribution from a tacfoot checkout or "
            f"an installed wheel that carries its source files, and {REPO} has neither (no "
            f"{', '.join(missing)} beside it or in device/{PACKAGED}/source): run host "
            f"deploy from a checkout, or install a wheel built by this version's setup.py")


def project_version() -> str:
    """The version in pyproject.toml (the package being built)."""
    try:
        with open(source_file("pyproject.toml"), "rb") as fh:
            return str(tomllib.load(fh)["project"]["version"])
    except (OSError, KeyError, ValueError):
        return "0"


def add_arguments(s):
    """The ``host deploy`` options (shared with host/cli/__init__.py)."""
    s.add_argument("target", nargs="*",
                   help="[USER@]HOST[:PORT] of each leg's Pi (several: one release on "
                        "every leg, or on none)")
    s.add_argument("--robot", metavar="FILE",
                   help="a robot file listing the legs ([[leg]] target, config, ...)")
    s.add_argument("--status", action="store_true",
                   help="show each leg's release and health, change nothing")
    s.add_argument("--dry-run", action="store_true", help="print the plan, touch nothing")
    s.add_argument("--rollback", action="store_true",
                   help="switch current back to the previous release and restart (one leg)")
    s.add_argument("--port", type=int, help="SSH port")
    s.add_argument("--identity", help="SSH private key file")
    s.add_argument("--ssh-option", action="append", default=[], metavar="OPT",
                   help="extra ssh -o option, e.g. StrictHostKeyChecking=no (repeatable)")
    s.add_argument("--prefix", default="/opt/tacfoot", help="install folder on the Pi")
    s.add_argument("--models", help="models folder to ship (default: models/)")
    s.add_argument("--config", help="runtime config TOML to ship (default: device/leg.toml)")
    s.add_argument("--python", default="python3", help="Python on the Pi to build the venv with")
    s.add_argument("--service-manager", choices=MANAGERS, default="auto",
                   help="systemd, or none (pid file + tacfootctl); auto probes the Pi")
    s.add_argument("--service-name", default="tacfoot", help="systemd unit / pid file name")
    s.add_argument("--service-user", help="User= of the unit (default: the SSH user)")
    s.add_argument("--unit-dir", default="/etc/systemd/system",
                   help="where the unit file is installed on the Pi")
    s.add_argument("--system-site-packages", action="store_true",
                   help="the venv sees the packages --python sees (e.g. apt's numpy/opencv)")
    s.add_argument("--no-deps", action="store_true",
                   help="pip install the package alone, offline (its deps and setuptools already on the Pi)")
    s.add_argument("--camera", default="v4l2:///dev/video0", help="runtime --camera source")
    s.add_argument("--imu", default="i2c://1/0x68", help="runtime --imu source")
    s.add_argument("--serial", default="/dev/serial0", help="runtime --serial port or URL")
    s.add_argument("--runtime-module", default="device.pi",
                   help="module the service runs as `python -m MODULE run ...`")
    s.add_argument("--runtime-arg", action="append", default=[], metavar="ARG",
                   help="extra argument for the runtime (repeatable; use --runtime-arg=--x)")
    s.add_argument("--env", action="append", default=[], metavar="KEY=VALUE",
                   help="environment variable for the service (repeatable)")
    s.add_argument("--watchdog-s", type=int, default=10, help="WatchdogSec= of the unit")
    s.add_argument("--health-timeout-s", type=float, default=60.0,
                   help="how long the health check waits for packets to flow")
    s.add_argument("--keep", type=int, default=3, help="releases kept on the Pi")
    s.add_argument("--release", help="release folder name (default: VERSION-UTCSTAMP-RAND)")
    s.add_argument("--signing-key", metavar="PATH",
                   help="the host's Ed25519 key that signs models and releases (default: "
                        "$TACFOOT_SIGNING_KEY or ~/.config/tacfoot/signing-key.pem; made "
                        "on first use)")
    s.add_argument("--allow-unsigned", action="store_true",
                   help="let the leg load unsigned models (signing.allow_unsigned = true)")
    s.add_argument("--json", action="store_true")


def options_from_args(a, target: str | None = None) -> DeployOptions:
    """The options of one leg: ``target``, or the only one given."""
    if target is None:
        target = a.target[0] if len(a.target) == 1 else ""
    return DeployOptions(
        target=target, port=a.port, identity=a.identity, ssh_options=a.ssh_option,
        prefix=a.prefix, models=a.models, config=a.config, python=a.python,
        service_manager=a.service_manager, service_name=a.service_name,
        service_user=a.service_user, unit_dir=a.unit_dir,
        system_site_packages=a.system_site_packages, no_deps=a.no_deps, camera=a.camera,
        imu=a.imu, serial=a.serial,
        runtime_module=a.runtime_module, runtime_args=a.runtime_arg, env=a.env,
        watchdog_s=a.watchdog_s, health_timeout_s=a.health_timeout_s, keep=a.keep,
        release=a.release, signing_key=a.signing_key, allow_unsigned=a.allow_unsigned)

