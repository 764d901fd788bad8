"""Rewrite a damaged, cut or unfinalized MCAP recording into a valid, finalized one: every
message the damage-tolerant scanner can read, with its sequence number and times; messages
whose payload is not a JSON object are left out."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from mcap.writer import CompressionType, Writer

from spiel_edge import __version__
from spiel_edge.recordings.mcap_reader import (
    ACQUISITION_TOPIC,
    BACKGROUND_TOPIC,
    POSITION_TOPIC,
    load_payload,
    open_recording,
    scan_limits,
    topic_of,
)
from spiel_edge.recordings.mcap_scan import McapScanner, ScanReport
from spiel_edge.safety.guard import atomic_write
from spiel_edge.safety.limits import InputLimits


@dataclass
class Recovered:
    messages: dict[str, int]  # kept, per topic
    dropped: int  # readable records whose payload was not a JSON object
    report: ScanReport

    @property
    def lost_data(self) -> bool:
        return self.dropped > 0 or self.report.damaged or self.report.truncated

    def summary(self) -> str:
        kept = ", ".join(f"{n} {t.rsplit('/', 1)[-1]}" for t, n in self.messages.items())
        dropped = f"; {self.dropped} unreadable messages left out" if self.dropped else ""
        return f"kept {kept or 'nothing'}{dropped}; input: {self.report.summary()}"


def recover(src: str | Path, dst: str | Path, limits: InputLimits | None = None) -> Recovered:
    """Write what can be read of ``src`` to ``dst`` (atomically: a temporary file renamed)."""
    from spiel_edge.recordings.mcap_writer import (
        ACQUISITION_SCHEMA,
        BACKGROUND_SCHEMA,
        MCAP_PROFILE,
        POSITION_SCHEMA,
    )

    limits = limits or InputLimits()
    schemas = {
        ACQUISITION_TOPIC: ACQUISITION_SCHEMA,
        BACKGROUND_TOPIC: BACKGROUND_SCHEMA,
        POSITION_TOPIC: POSITION_SCHEMA,
    }
    kept = dict.fromkeys(schemas, 0)
    dropped = 0
    with open_recording(Path(src)) as (fh, size), atomic_write(dst, "wb") as out:
        scanner = McapScanner(fh, size, scan_limits(limits))
        writer = Writer(out, compression=CompressionType.ZSTD, chunk_size=32 * 1024)
        writer.start(profile=MCAP_PROFILE, library=f"spiel-edge {__version__} (recover)")
        channels = {}
        for topic, schema in schemas.items():
            sid = writer.register_schema(schema["title"], "jsonschema", json.dumps(schema).encode())
            channels[topic] = writer.register_channel(topic, "json", sid)
        for msg in scanner.messages():
            topic = topic_of(msg)
            try:
                load_payload(msg.data)
            except ValueError:
                dropped += 1
                continue
            writer.add_message(
                channels[topic],
                log_time=msg.log_time,
                data=msg.data,
                publish_time=msg.publish_time,
                sequence=msg.sequence,
            )
            kept[topic] += 1
        writer.add_metadata(
            "spiel-edge", {"version": __version__, "recovered_from": Path(src).name}
        )
        writer.finish()
    return Recovered(kept, dropped, scanner.report)
