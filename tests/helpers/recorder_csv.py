"""A data recorder's CSV log of a measured-data bag, written the way a recorder would, from the
public interface alone (docs/interfaces.md): this module reads the bag's MCAP file with the
``mcap``/``mcap_ros2`` libraries, not with the project's code, and knows nothing of the
project's generator or of ``csv2bag``'s internals.

One row per message in log-time order, as a recorder logging its bus:

- an odometer reading: ``t_ref`` (log time, s), ``t_train`` (its stamp, s), ``v_kmh``,
  ``odo_m`` and, where asked, ``n`` (its sample counter, the message's ``seq``);
- a balise reading: ``t_ref``, ``t_train``, ``balise`` (id) and ``balise_m`` (position);
- a command: ``t_ref``, ``trac`` and ``brake`` (m/s^2, both >= 0).

A lost sample has no row (the radio link lost it before the recorder): without the counter the
CSV says nothing else about it. ``columns`` of the map file (csv2bag --map) say which column is
which; the odometer's and the balises' stated standard deviations go into it too.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import yaml

HEADER = ["t_ref", "t_train", "n", "v_kmh", "odo_m", "balise", "balise_m", "trac", "brake"]


def _messages(bag: Path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    files = sorted(Path(bag).glob("*.mcap")) if Path(bag).is_dir() else [Path(bag)]
    for f in files:
        with open(f, "rb") as fh:
            reader = make_reader(fh, decoder_factories=[DecoderFactory()])
            for _, channel, message, msg in reader.iter_decoded_messages(log_time_order=True):
                yield channel.topic.rsplit("/", 1)[-1], message.log_time, msg


def _secs(stamp) -> str:
    return f"{stamp.sec}.{stamp.nanosec:09d}"


def _log(ns: int) -> str:
    return f"{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}"


COUNTERS = ("seq", "none", "rows")


def write_csv(bag: str | Path, out_csv: str | Path, out_map: str | Path,
              counter: str = "seq") -> dict:
    """Write the bag's odometer, balise and control messages as a CSV log and its map file.
    ``counter``: the odometer's sample counter column holds the message's ``seq`` ("seq"), is
    left out ("none": the losses are only missing rows), or numbers the odometer rows ("rows":
    a log that counts its own rows, which hides the losses). Returns row counts by kind."""
    assert counter in COUNTERS, counter
    rows, counts = [], {"odometer": 0, "balise": 0, "control": 0}
    speed_var, balise_var = [], []
    for topic, log_ns, msg in _messages(bag):
        if topic == "odometer":
            rows.append((log_ns, 1, {"t_ref": _log(log_ns), "t_train": _secs(msg.header.stamp),
                                     "n": str(msg.seq),
                                     "v_kmh": repr(msg.speed * 3.6), "odo_m": repr(msg.distance)}))
            speed_var.append(msg.speed_variance)
        elif topic == "balise":
            rows.append((log_ns, 2, {"t_ref": _log(log_ns), "t_train": _secs(msg.header.stamp),
                                     "balise": str(msg.balise_id),
                                     "balise_m": repr(msg.position)}))
            balise_var.append(msg.position_variance)
        elif topic == "control":
            a = msg.target_acceleration
            rows.append((log_ns, 0, {"t_ref": _log(log_ns), "trac": repr(max(a, 0.0)),
                                     "brake": repr(max(-a, 0.0))}))
        else:
            continue
        counts[topic] += 1
    rows.sort(key=lambda r: (r[0], r[1]))
    n_odo = 0
    for _, kind, r in rows:
        if kind == 1:
            n_odo += 1
            r["n"] = {"seq": r["n"], "none": "", "rows": str(n_odo)}[counter]
    with open(out_csv, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=HEADER)
        w.writeheader()
        for _, _, r in rows:
            w.writerow(r)
    columns = {"time": "t_ref", "train_time": "t_train", "speed": "v_kmh", "distance": "odo_m",
               "balise": "balise", "balise_position": "balise_m", "traction": "trac",
               "braking": "brake"}
    if counter != "none":
        columns["sample"] = "n"
    mapping = {"columns": columns, "units": {"speed": "km/h"},
               "speed_std": math.sqrt(max(speed_var)) if speed_var else 0.1,
               "balise_std": math.sqrt(max(balise_var)) if balise_var else 1.0}
    Path(out_map).write_text(yaml.safe_dump(mapping, sort_keys=False))
    return counts
