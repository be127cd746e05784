"""An MCAP file read back with the ``mcap`` package's own reader, for the tests of
the commands that write one (``--mcap``)."""
from __future__ import annotations

import json


def read_mcap(path) -> tuple[dict, dict]:
    """(topic -> schema name, topic -> [(log_time ns, decoded JSON)] in file order).
    The summary is read too, so a file without its footer fails here."""
    from mcap.reader import make_reader
    with open(path, "rb") as fh:
        r = make_reader(fh)
        summary = r.get_summary()
        schemas = {s.id: s.name for s in summary.schemas.values()}
        chans = {c.topic: schemas[c.schema_id] for c in summary.channels.values()}
        msgs: dict[str, list] = {}
        for _, ch, m in r.iter_messages(log_time_order=False):
            msgs.setdefault(ch.topic, []).append((m.log_time, json.loads(m.data)))
    return chans, msgs
