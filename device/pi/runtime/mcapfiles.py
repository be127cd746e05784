"""The files of the leg's MCAP log (:mod:`device.pi.runtime.mcaplog`): their names,
the counting file they are written through, the run's Metadata record
(:func:`run_metadata`), and reading them back.

Names: ``run.mcap``, then ``run-0001.mcap``, ``run-0002.mcap`` ... as the log rolls
over (:func:`roll_name`). The runtime's log never truncates a file: when ``run.mcap``
or any of its roll files already exists (the last run's, perhaps a crashed one's),
the run is written under the next free name (:func:`free_name`): ``run.1.mcap``
(then ``run.1-0001.mcap`` ...), ``run.2.mcap`` ...; files are created exclusively,
so a roll-over skips a name that appeared meanwhile.

Reading back: a file cut short by a crash has no footer; :func:`read_log` reads its
complete chunks, and :func:`recover` rewrites them as a well-formed file. A file cut
inside its 8-byte magic (even empty) holds no message; one that does not start with
the magic is a :class:`McapLogError` naming it.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

from device.pi.runtime.mcapmsg import channels
from device.errors import TacfootError

#: ``--mcap-max-mb`` bounds, MB: below ~1 MB a file is mostly schemas and summary
MAX_MB_MIN = 1.0
MAX_MB_MAX = 1_048_576.0
INSTALL_HINT = "MCAP logging needs the viz extra: pip install .[viz]"


class McapLogError(TacfootError, OSError):
    """The MCAP log cannot be opened (no ``mcap`` package, a bad path)."""


def roll_name(path: Path, n: int) -> Path:
    """The n-th file of a log: ``run.mcap``, ``run-0001.mcap``, ..."""
    return path if n == 0 else path.with_name(f"{path.stem}-{n:04d}{path.suffix}")


def free_name(path: Path) -> Path:
    """``path`` when neither it nor any of its roll files exists; else the first of
    ``run.1.mcap``, ``run.2.mcap`` ... of which none exists (a log is never
    truncated). The folder is listed once."""
    try:
        names = set(os.listdir(path.parent))
    except OSError:
        return path                   # opening the file will say why
    stem, suffix = path.stem, path.suffix
    rolled = set()                    # the stems that have roll files: run of run-0001
    for name in names:
        if name.endswith(suffix):
            base, dash, num = name[:len(name) - len(suffix)].rpartition("-")
            if dash and num.isdigit():
                rolled.add(base)

    def taken(s: str) -> bool:
        return s + suffix in names or s in rolled
    if not taken(stem):
        return path
    k = 1
    while taken(f"{stem}.{k}"):
        k += 1
    return path.with_name(f"{stem}.{k}{suffix}")


def writer_module():
    try:
        from mcap import writer
    except ImportError:
        raise McapLogError(INSTALL_HINT) from None
    return writer


class CountingFile:
    """An unbuffered file that counts the bytes written (the roll-over size) and the
    writes that completed. ``exclusive``: never an existing file (FileExistsError)."""

    def __init__(self, path: Path, exclusive: bool = False):
        self.fh = open(path, "xb" if exclusive else "wb", buffering=0)
        self.size = 0
        self.writes = 0

    def write(self, data) -> int:
        n = len(data)
        mv = memoryview(data)
        done = 0
        while done < n:                       # a raw write may take less than asked
            k = self.fh.write(mv[done:])
            if not k:
                raise OSError("the file took no bytes")
            done += k
        self.size += n
        self.writes += 1
        return n

    def tell(self) -> int:
        return self.size

    def flush(self) -> None:
        pass

    def close(self) -> None:
        self.fh.close()


def run_metadata(rt) -> dict:
    """The ``tacfoot`` Metadata record of a run (MCAP metadata values are strings):
    the package version, the sensor profile's name and hash, each loaded model's
    hashes (its manifest's ``sha256``, JSON) and the leg config (JSON)."""
    from dataclasses import asdict
    from importlib.metadata import PackageNotFoundError, version
    try:
        ver = version("tacfoot")
    except PackageNotFoundError:
        ver = "unknown"
    models = rt.models
    prof = models.profile or {}
    hashes = {}
    for name in ("surface", "texture", "slip", "pressure", "localiser"):
        mod = getattr(models, name, None)
        spec = (getattr(getattr(mod, "model", None), "spec", None)
                or getattr(mod, "spec", None))
        if spec is not None:
            hashes[name] = spec.sha256
    return {"version": ver, "profile": str(prof.get("name") or models.profile_source or ""),
            "profile_sha256": str(prof.get("sha256") or ""),
            "models": json.dumps(hashes, sort_keys=True),
            "config": json.dumps(asdict(rt.cfg), sort_keys=True, default=str)}


#: the first 8 bytes of every MCAP file
MAGIC = b"\x89MCAP0\r\n"


def read_log(path) -> tuple[list[dict], bool]:
    """The messages of one MCAP file in file order, as dicts (``topic``, ``schema``,
    ``log_time``, ``data``: the decoded JSON), and whether the file was complete.
    A file cut short (a crash) gives the messages of its complete chunks; one cut
    inside its 8-byte magic (even empty) none. A file that does not start as an MCAP
    file is a :class:`McapLogError` naming it."""
    try:
        from mcap.exceptions import McapError
        from mcap.records import Channel, Chunk, Message, Schema
        from mcap.stream_reader import StreamReader, breakup_chunk
    except ImportError:
        raise McapLogError(INSTALL_HINT) from None
    schemas, channels, out = {}, {}, []
    complete = False

    def take(rec):
        if isinstance(rec, Schema):
            schemas[rec.id] = rec.name
        elif isinstance(rec, Channel):
            channels[rec.id] = (rec.topic, rec.schema_id)
        elif isinstance(rec, Message):
            topic, sid = channels[rec.channel_id]
            out.append({"topic": topic, "schema": schemas.get(sid), "log_time": rec.log_time,
                        "data": json.loads(rec.data)})

    with open(path, "rb") as fh:
        head = fh.read(len(MAGIC))
        if head != MAGIC:
            if MAGIC.startswith(head):    # cut inside the magic: nothing to read
                return out, False
            raise McapLogError(f"{path}: not an MCAP file (it starts {head!r}, not "
                               f"MCAP's magic {MAGIC!r})")
        fh.seek(0)
        try:
            for rec in StreamReader(fh, skip_magic=False, emit_chunks=True).records:
                if isinstance(rec, Chunk):
                    for r in breakup_chunk(rec, validate_crc=True):
                        take(r)
                else:
                    take(rec)
            complete = True
        except (McapError, EOFError, ValueError, KeyError, OSError):
            pass                          # cut short: what came before stands
    return out, complete


def recover(src, dst) -> int:
    """Rewrite the readable prefix of ``src`` (a log cut short by a crash) as a
    well-formed MCAP file ``dst``; the number of messages kept."""
    W = writer_module()
    msgs, _ = read_log(src)
    known = channels()
    topics = {**known, **{m["topic"]: {"title": m["schema"]} for m in msgs
                          if m["topic"] not in known}}
    with open(dst, "wb") as fh:
        w = W.Writer(fh, compression=W.CompressionType.ZSTD)
        w.start(profile="", library="tacfoot")
        sids, cids = {}, {}
        for topic, schema in topics.items():
            name = schema["title"]
            if name not in sids:
                sids[name] = w.register_schema(name, "jsonschema", json.dumps(schema).encode())
            cids[topic] = w.register_channel(topic, "json", sids[name])
        for m in msgs:
            w.add_message(cids[m["topic"]], log_time=m["log_time"],
                          publish_time=m["log_time"], data=json.dumps(m["data"]).encode())
        w.finish()
    return len(msgs)
