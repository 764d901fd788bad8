"""Cost of the ROS 2 encoding per acquisition (`spiel-edge bench`, key ``ros2_encoding``).

Per record: the PointStamped of the best target plus the PointCloud2 of its targets (what the
ros2 MCAP recording and Zenoh cdr add), with 1 and 3 targets; beside it, in the same run, the
JSON encoding of the same record that every record already costs (a ratio that stays
meaningful on a busy machine). With a static transform (the profile's ``[frame]``): the
Zenoh cdr path's messages per record (outputs/zenoh_ros2.CdrMessages: point, cloud and the
check whether /tf_static is due) plus one TFMessage encoding spread over the acquisitions of
its period (TF_PERIOD_S at 50 Hz; a ros2 MCAP writes it once per file). Target: <= 5 us per
acquisition.
"""

from __future__ import annotations

import json
import time

import numpy as np

from spiel_edge.outputs.ros2 import frame_settings
from spiel_edge.outputs.zenoh_ros2 import TF_PERIOD_S, CdrMessages
from spiel_edge.profile.frame_section import FrameSpec
from spiel_edge.recordings.cdr import Ros2Encoder

RATE_HZ = 50.0  # `run --rate`'s default


def _records(count: int, n_targets: int, seed: int = 0) -> list[dict]:
    rng = np.random.default_rng(seed)
    records = []
    for i in range(count):
        targets = [
            {
                "position_mm": [round(float(v), 2) for v in rng.uniform(-150, 150, 3)],
                "covariance_mm2": [[4.0, 0.1, 0.0], [0.1, 9.0, 0.0], [0.0, 0.0, 16.0]],
                "residual_mm": 1.0,
                "matched": [0, 0, 1, 0],
                "score": 0.5,
                "track_id": i % 5,
            }
            for _ in range(n_targets)
        ]
        records.append(
            {
                "seq": i,
                "host_time": 1.7e9 + i / 50,
                "position_mm": targets[0]["position_mm"],
                "targets": targets,
            }
        )
    return records


def _best_us(fn, records: list[dict], repeat: int, burst: int = 50) -> float:
    """Best time per record over short bursts: a burst fits in one scheduler slice, so the
    minimum resists a machine shared with other work (a long loop would measure the sharing)."""
    best = float("inf")
    for _ in range(repeat):
        for start in range(0, len(records) - burst + 1, burst):
            chunk = records[start : start + burst]
            t0 = time.perf_counter()
            for record in chunk:
                fn(record)
            best = min(best, (time.perf_counter() - t0) / burst)
    return round(best * 1e6, 2)


def ros2_encoding_us(count: int = 2000, repeat: int = 5) -> dict:
    encoder = Ros2Encoder("spiel")

    def ros2(record: dict) -> None:
        encoder.point_stamped(record["position_mm"], record["host_time"])
        encoder.targets_cloud(record["targets"], record["host_time"])

    def point_only(record: dict) -> None:
        encoder.point_stamped(record["position_mm"], record["host_time"])

    def as_json(record: dict) -> None:
        json.dumps(record, separators=(",", ":"), allow_nan=False)

    one, three = _records(count, 1), _records(count, 3)
    mount = FrameSpec(parent="base_link", translation_m=(0.1, 0.0, 0.25))
    messages = CdrMessages(frame_settings(mount, rotation_rpy_deg=(0.0, 0.0, 90.0)))
    messages.of_record(three[0])  # the transform just sent: the check is what each record pays
    with_tf = _best_us(messages.of_record, three, repeat)
    tf_us = _best_us(lambda _record: messages.tf_message(), three, repeat)
    return {
        "point_stamped_us": _best_us(point_only, one, repeat),
        "point_and_cloud_1_target_us": _best_us(ros2, one, repeat),
        "point_and_cloud_3_targets_us": _best_us(ros2, three, repeat),
        "json_record_3_targets_us": _best_us(as_json, three, repeat),
        "cdr_messages_3_targets_with_tf_us": with_tf,
        "tf_static_message_us": tf_us,
        "with_tf_per_acquisition_3_targets_us": round(with_tf + tf_us / (TF_PERIOD_S * RATE_HZ), 2),
        "target_us": 5.0,
    }
