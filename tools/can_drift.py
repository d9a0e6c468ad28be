"""Drift of CAN dead reckoning against the ground-truth trajectory of the comma2k19 RAV4 segment.

Usage: .venv/bin/python tools/can_drift.py [DATA_DIR]
(DATA_DIR default: ../shared/data/comma2k19-rav4-segment, or $SCUBE_SIM_SHARED_DATA/...)

Dead-reckons WHEEL_SPEEDS + STEER_ANGLE_SENSOR (can0) with `scube_sim.sim.can` and compares it
with `global_pose` (20 Hz, ECEF, converted to ENU at the first pose; horizontal error).
Alignment: the start position is the ground truth's at the first dead-reckoned instant; the
heading rotates the dead-reckoned chord over the first 1 s onto the ground-truth chord over the
same second. The final heading error is the difference of the heading *changes* from start to
end (ground-truth heading = direction of its velocity), so it does not depend on the
alignment. Reported for the nominal RAV4 parameters and for a calibration (steering zero offset,
effective steering ratio, wheel-speed scale) fitted on the first 20 s only.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from scube_sim.geodesy import ecef_to_enu, ecef_to_geodetic, enu_rotation  # noqa: E402
from scube_sim.sim.can import CanPoseSource, CanVehicleDecoder  # noqa: E402
from scube_sim.sim.vehicle import DeadReckoner, calibrate_bicycle  # noqa: E402
from scube_sim.transforms import euler_to_rotmat, make_pose  # noqa: E402

LOG = "converted/raw_can_candump.log.gz"
DBC = "dbc/toyota_rav4_2017_pt_generated.dbc"


def load_ground_truth(root: Path):
    """(times s boot clock, ENU positions (N, 3) m, ENU velocities (N, 3) m/s) at the first pose."""
    g = root / "segment" / "global_pose"
    t = np.load(g / "frame_times")
    p = np.load(g / "frame_positions")
    v = np.load(g / "frame_velocities")
    lat, lon, _ = ecef_to_geodetic(p[0])
    return t, ecef_to_enu(p, p[0]), v @ enu_rotation(lat, lon)


def drift(src: CanPoseSource, gt_t, gt_enu, gt_vel, chord_s: float = 1.0) -> dict:
    """Align `src` (its reckoner re-based to the ground truth) and measure the horizontal drift."""
    t_gt = gt_t - src.time_offset  # ground-truth times on the source clock
    ts = src.times
    t0, t1 = ts[0], ts[-1]
    # start: GT position at the first DR instant; heading: GT chord vs DR chord over chord_s
    p0 = np.array([np.interp(t0, t_gt, gt_enu[:, k]) for k in range(3)])
    pc = np.array([np.interp(t0 + chord_s, t_gt, gt_enu[:, k]) for k in range(3)])
    gt_h = np.arctan2(pc[1] - p0[1], pc[0] - p0[0])
    dr0, drc = src.pose_at(t0)[:3, 3], src.pose_at(t0 + chord_s)[:3, 3]
    dr_h = np.arctan2(drc[1] - dr0[1], drc[0] - dr0[0])
    align = make_pose(euler_to_rotmat(0.0, 0.0, gt_h - dr_h), [p0[0], p0[1], 0.0]) @ \
        np.linalg.inv(src.pose_at(t0))
    sel = (t_gt >= t0) & (t_gt <= t1)
    tq = t_gt[sel]
    dr = (align @ src.pose_at(tq))[:, :2, 3]
    err = np.linalg.norm(dr - gt_enu[sel, :2], axis=1)
    # heading drift: DR yaw change vs GT velocity-heading change, start to end
    states = src.reckoner.states
    dyaw_dr = np.interp(t1, ts, states[:, 2]) - np.interp(t0, ts, states[:, 2])
    hdg = np.unwrap(np.arctan2(gt_vel[:, 1], gt_vel[:, 0]))
    dyaw_gt = np.interp(t1, t_gt, hdg) - np.interp(t0, t_gt, hdg)
    seg = gt_enu[sel]
    path = float(np.linalg.norm(np.diff(seg, axis=0), axis=1).sum())
    return {"span_s": float(t1 - t0), "path_m": path, "final_m": float(err[-1]), "max_m": float(err.max()),
            "final_pct": 100.0 * float(err[-1]) / path, "heading_deg": float(np.degrees(dyaw_dr - dyaw_gt)),
            "gt_heading_change_deg": float(np.degrees(dyaw_gt))}


def calibrate(root: Path, gt_t, gt_vel, t_from: float, t_to: float, smooth_s: float = 1.0):
    """(steer_ratio, steer_offset_deg, speed_scale) fitted on boot-clock [t_from, t_to]:
    ratio and offset by `calibrate_bicycle` against the GT yaw rate (velocity heading
    differentiated, `smooth_s` moving average), speed scale = GT distance / CAN distance."""
    can_dir = root / "segment" / "processed_log" / "CAN"
    sp_t, sp = np.load(can_dir / "speed" / "t"), np.load(can_dir / "speed" / "value")[:, 0]
    st_t, st = np.load(can_dir / "steering_angle" / "t"), np.load(can_dir / "steering_angle" / "value")
    sel = (gt_t >= t_from) & (gt_t <= t_to)
    t = gt_t[sel]
    hdg = np.unwrap(np.arctan2(gt_vel[:, 1], gt_vel[:, 0]))
    rate = np.gradient(hdg, gt_t)[sel]
    k = max(1, int(round(smooth_s / np.median(np.diff(t)))))
    box = np.ones(k) / k
    sm = lambda a: np.convolve(a, box, mode="same")  # noqa: E731
    v = np.interp(t, sp_t, sp)
    sw = np.interp(t, st_t, st)
    ratio, offset = calibrate_bicycle(t, sm(v), sm(sw), sm(rate))
    scale = float(np.linalg.norm(gt_vel[sel], axis=1).sum() / v.sum())
    return ratio, offset, scale


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv:
        root = Path(argv[0])
    else:
        env = os.environ.get("SCUBE_SIM_SHARED_DATA")
        base = Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "data"
        root = base / "comma2k19-rav4-segment"
    if not (root / LOG).is_file():
        print(f"missing {root / LOG}", file=sys.stderr)
        return 2
    gt_t, gt_enu, gt_vel = load_ground_truth(root)
    decoder = CanVehicleDecoder(root / DBC, channels=("can0",))

    def run(start, stop, **params):
        src = CanPoseSource.from_log(root / LOG, decoder=decoder, reckoner=DeadReckoner(**params),
                                     start=start, stop=stop)
        return drift(src, gt_t, gt_enu, gt_vel)

    nominal = {}
    print("CAN dead reckoning vs comma2k19 global_pose (RAV4, 2018-08-02, segment 40)")
    print("model: kinematic bicycle, rear axle; speed = mean of 4 wheel speeds (0xAA) / 3.6; "
          "steering = STEER_ANGLE + STEER_FRACTION (0x25); can0")
    hdr = f"{'window':>10} {'span s':>7} {'path m':>8} {'final m':>8} {'max m':>7} {'% path':>7} " \
          f"{'hdg err deg':>11} {'GT turn deg':>11}"

    def show(label, r):
        print(f"{label:>10} {r['span_s']:7.2f} {r['path_m']:8.1f} {r['final_m']:8.2f} {r['max_m']:7.2f} "
              f"{r['final_pct']:7.2f} {r['heading_deg']:11.2f} {r['gt_heading_change_deg']:11.2f}")

    windows = [(0.0, None), (0.0, 20.0), (20.0, 40.0), (40.0, None)]
    print("\nnominal: wheelbase 2.66 m, steer ratio 15.7, steer offset 0 deg, speed scale 1")
    print(hdr)
    for start, stop in windows:
        r = run(start, stop)
        nominal[(start, stop)] = r
        show(f"{start:g}-{'60' if stop is None else f'{stop:g}'} s", r)

    src = CanPoseSource.from_log(root / LOG, decoder=decoder, start=0.0, stop=20.0)
    t_a = src.time_offset
    ratio, offset, scale = calibrate(root, gt_t, gt_vel, t_a, t_a + 20.0)
    print(f"\ncalibrated on 0-20 s: effective steer ratio {ratio:.2f}, steer offset {offset:+.3f} deg, "
          f"speed scale {scale:.5f}")
    for label, params in (("offset only", {"steer_offset_deg": offset}),
                          ("offset+scale", {"steer_offset_deg": offset, "speed_scale": scale}),
                          ("all three", {"steer_offset_deg": offset, "speed_scale": scale,
                                         "steer_ratio": ratio})):
        print(f"\n{label}: " + ", ".join(f"{k} {v:.5g}" for k, v in params.items()))
        print(hdr)
        for start, stop in windows:
            show(f"{start:g}-{'60' if stop is None else f'{stop:g}'} s", run(start, stop, **params))
    ratio60, offset60, scale60 = calibrate(root, gt_t, gt_vel, t_a, t_a + 60.0)
    print(f"\n(fit over all 60 s: effective steer ratio {ratio60:.2f}, offset {offset60:+.3f} deg, "
          f"speed scale {scale60:.5f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
