"""A run's summary as plain JSON-able data (stations served, stopping errors, link losses)."""

from __future__ import annotations


def run_summary(res) -> dict:
    """Summarise a :class:`train_sim.world.SimResult` for reports and the main job."""
    link = {}
    for topic in ("odometer", "balise"):
        sent = int(res.sent.get(topic, 0))
        dropped = int(res.dropped.get(topic, 0))
        link[topic] = {"sent": sent, "dropped": dropped,
                       "received_fraction": (sent - dropped) / sent if sent else float("nan")}
    return {
        "scenario": res.scenario,
        "seed": int(res.seed),
        "t_end": float(res.duration),
        "stops": [{"station": s["station"], "position": float(s["position"]),
                   "stop_position": float(s["stop_position"]),
                   "stopping_error": float(s["stopping_error"]), "t": float(s["t"])}
                  for s in res.stops],
        "emergency_brakes": int(res.emergency_brakes),
        "link": link,
    }
