// Foxglove user script of docs/foxglove_layout.json (kept in sync by tests/test_demo_outputs.py).
// Errors of the estimates against ground truth, matched by sample stamp: one output message per
// estimate on /studio_script/train_errors, with the estimator's name in `source` (the layout's
// plots select one estimator each with {source=="..."}: robust_filter, gsma, kf). Topics are in
// the /train namespace, as the main job records them.
type Time = { sec: number; nsec: number };

type Output = {
  header: { stamp: Time; frame_id: string };
  source: string;
  position_error: number; // m, estimate - truth
  velocity_error: number; // m/s
  braking_rate_error: number; // -, NaN where the estimator does not estimate it
  position_3sigma: number; // m, 3 x the stated standard deviation
  velocity_3sigma: number; // m/s
};

export const inputs = [
  "/train/ground_truth",
  "/train/estimate/robust",
  "/train/estimate/gsma",
  "/train/estimate/kf",
];
export const output = "/studio_script/train_errors";

const truth = new Map<number, { position: number; velocity: number; braking_rate: number }>();
let newest = 0;

function stampMs(stamp: { sec: number; nsec?: number; nanosec?: number }): number {
  return Math.round(stamp.sec * 1e3 + (stamp.nsec ?? stamp.nanosec ?? 0) / 1e6);
}

export default function script(event: { topic: string; message: any }): Output | undefined {
  const m = event.message;
  const key = stampMs(m.header.stamp);
  if (event.topic === "/train/ground_truth") {
    truth.set(key, { position: m.position, velocity: m.velocity, braking_rate: m.braking_rate });
    newest = Math.max(newest, key);
    for (const k of truth.keys()) {
      if (k < newest - 120000) truth.delete(k); // keep two minutes of truth
    }
    return undefined;
  }
  const t = truth.get(key); // estimates share the truth's sample grid
  if (t === undefined) return undefined;
  const cov: number[] = Array.from(m.covariance);
  return {
    header: { stamp: { sec: Math.floor(key / 1e3), nsec: (key % 1e3) * 1e6 }, frame_id: "track" },
    source: m.source,
    position_error: m.position - t.position,
    velocity_error: m.velocity - t.velocity,
    braking_rate_error: m.braking_rate - t.braking_rate,
    position_3sigma: 3 * Math.sqrt(Math.max(cov[0], 0)),
    velocity_3sigma: 3 * Math.sqrt(Math.max(cov[5], 0)),
  };
}
