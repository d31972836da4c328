"""KITTI odometry 01's recorded poses against the raw images' own geometry, for bench/kitti_pose_check.py (no map):
SIFT matches of the raw frames under the recorded relative poses (Sampson error) against an essential matrix fitted
to them; the road's plane-induced homography between consecutive frames (the along-track step, which epipolar
geometry cannot see); the track's speed jitter; and whether a view's map-fitted rigid correction makes its frame's
matches agree better with the poses (a real pose error would).
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
from kitti_error import DATA

from importers.kitti_files import calibration_matrix, read_calibration
from importers.kitti_odometry import KITTI_ODOMETRY_CALIBRATION, read_poses
from mapping.localization.camera_orientation import ratio_matches

FOLDER = DATA / "kitti_odometry_01"


def recorded_poses_and_k() -> tuple[np.ndarray, np.ndarray]:
    """The sequence's camera 0 -> world poses (N, 4, 4) and its K (from P0), read as the importer reads them."""
    calib = FOLDER / "calib.txt"
    p0 = calibration_matrix(read_calibration(calib, unnamed=KITTI_ODOMETRY_CALIBRATION), "P0", (3, 4), calib)
    return read_poses(FOLDER / "poses.txt"), p0[:, :3]


def inlier_matches(feat_a, feat_b, k: np.ndarray, matcher) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ratio-test matches that an essential matrix fitted to them (RANSAC, 1 px) keeps, and that matrix."""
    p1, p2 = ratio_matches(feat_a, feat_b, matcher)
    e, inl = cv2.findEssentialMat(p1, p2, k, cv2.RANSAC, 0.999, 1.0)
    inl = inl.ravel() > 0
    return p1[inl], p2[inl], e


def rotation(w: torch.Tensor) -> torch.Tensor:
    k = torch.zeros(3, 3, dtype=w.dtype)
    k[0, 1], k[0, 2], k[1, 2] = -w[2], w[1], -w[0]
    k[1, 0], k[2, 0], k[2, 1] = w[2], -w[1], w[0]
    return torch.linalg.matrix_exp(k)


def correction_matrix(p: np.ndarray) -> np.ndarray:
    """4x4 camera-frame correction from (pitch, yaw, roll in mrad, x, y, z in cm)."""
    m = np.eye(4)
    m[:3, :3] = rotation(torch.tensor(p[:3] * 1e-3, dtype=torch.float64)).numpy()
    m[:3, 3] = p[3:6] * 1e-2
    return m


def relative(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, t taking camera a's points into camera b's (x_b = R x_a + t); a, b camera-to-world 4x4."""
    rel = np.linalg.inv(b) @ a
    return rel[:3, :3], rel[:3, 3]


def skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])


def sampson(f: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    x1 = np.c_[p1, np.ones(len(p1))]
    x2 = np.c_[p2, np.ones(len(p2))]
    fx1, ftx2 = x1 @ f.T, x2 @ f
    num = (x2 * fx1).sum(1)
    return np.abs(num) / np.sqrt(fx1[:, 0] ** 2 + fx1[:, 1] ** 2 + ftx2[:, 0] ** 2 + ftx2[:, 1] ** 2)


def epipolar(gaps: tuple[int, ...]) -> dict:
    """Map-independent: the recorded relative poses against SIFT matches of the raw frames."""
    poses, k = recorded_poses_and_k()
    kinv = np.linalg.inv(k)
    images = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in sorted((FOLDER / "image_0").glob("*.png"))]
    sift = cv2.SIFT_create(nfeatures=4000)
    feats = [sift.detectAndCompute(im, None) for im in images]
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    out = {}
    for gap in gaps:
        rows = []
        for i in range(len(images) - gap):
            p1, p2, e = inlier_matches(feats[i], feats[i + gap], k, matcher)
            r_rec, t_rec = relative(poses[i], poses[i + gap])
            f_rec = kinv.T @ skew(t_rec) @ r_rec @ kinv
            _, r_e, t_e, _ = cv2.recoverPose(e, p1, p2, k)
            t_e = t_e.ravel()
            f_e = kinv.T @ skew(t_e) @ r_e @ kinv
            s_rec, s_e = sampson(f_rec, p1, p2), sampson(f_e, p1, p2)
            d_rot = cv2.Rodrigues(r_e @ r_rec.T)[0].ravel()  # fitted vs recorded, camera axes
            step = np.linalg.norm(t_rec)
            dirn = t_rec / step
            d_dir = t_e - dirn * (t_e @ dirn)  # the fitted direction's part across the recorded one (unit)
            far = p1[:, 1] < 185.2  # above the principal point: far scenery, rotation dominates
            rows.append({"frame": i, "matches": len(p1), "sampson_recorded_px": float(np.median(s_rec)),
                         "sampson_fitted_px": float(np.median(s_e)),
                         "sampson_recorded_rms_px": float(np.sqrt((s_rec ** 2).mean())),
                         "sampson_fitted_rms_px": float(np.sqrt((s_e ** 2).mean())),
                         "sampson_recorded_far_px": float(np.median(s_rec[far])) if far.any() else None,
                         "rot_diff_deg": np.degrees(d_rot).round(4).tolist(),
                         "dir_diff_cm": (100 * step * d_dir).round(2).tolist(), "step_m": float(step)})
        rec = np.array([r["sampson_recorded_px"] for r in rows])
        fit = np.array([r["sampson_fitted_px"] for r in rows])
        rot = np.array([r["rot_diff_deg"] for r in rows])
        dd = np.array([r["dir_diff_cm"] for r in rows])
        print(f"epipolar, frames {gap} apart ({len(rows)} pairs, {np.median([r['matches'] for r in rows]):.0f} "
              f"inlier matches median): Sampson median px, recorded pose {np.median(rec):.3f} (pairs "
              f"{rec.min():.3f}-{rec.max():.3f}) vs fitted E {np.median(fit):.3f}; fitted - recorded rotation "
              f"(pitch, yaw, roll) mean {rot.mean(0).round(3)} deg, std {rot.std(0).round(3)}; translation "
              f"direction across the recorded (lateral, down, along) x step: mean {dd.mean(0).round(2)} cm, std "
              f"{dd.std(0).round(2)}", flush=True)
        for r in rows:
            far = r["sampson_recorded_far_px"] or float("nan")
            print(f"  {r['frame']:2d}->{r['frame'] + gap:2d}: {r['matches']:4d} matches, Sampson "
                  f"{r['sampson_recorded_px']:.3f} / {r['sampson_fitted_px']:.3f} px (far {far:.3f}), rot diff "
                  f"{r['rot_diff_deg']} deg, dir diff {r['dir_diff_cm']} cm")
        out[f"gap_{gap}"] = {"pairs": len(rows), "sampson_recorded_median_px": round(float(np.median(rec)), 3),
                             "sampson_fitted_median_px": round(float(np.median(fit)), 3),
                             "rot_diff_mean_deg": rot.mean(0).round(4).tolist(),
                             "rot_diff_std_deg": rot.std(0).round(4).tolist(),
                             "dir_diff_mean_cm": dd.mean(0).round(2).tolist(),
                             "dir_diff_std_cm": dd.std(0).round(2).tolist(), "per_pair": rows}
    out["road_scale"] = road_scale(images, feats, poses, k)
    # speed jitter: the recorded camera centres against a smooth fit in frame index (10 Hz)
    centres = poses[:, :3, 3]
    n = np.arange(len(centres))
    smooth = np.stack([np.polyval(np.polyfit(n, centres[:, j], 5), n) for j in range(3)], 1)
    resid = centres - smooth
    forward = np.gradient(smooth, axis=0)
    forward /= np.linalg.norm(forward, axis=1, keepdims=True)
    along = (resid * forward).sum(1)
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    step_resid = steps - np.polyval(np.polyfit(n[1:], steps, 5), n[1:])
    lag1 = float(np.corrcoef(step_resid[:-1], step_resid[1:])[0, 1])
    out["track"] = {"speed_m_per_frame_min_max": [round(float(steps.min()), 3), round(float(steps.max()), 3)],
                    "position_resid_rms_cm": (100 * np.sqrt((resid ** 2).mean(0))).round(2).tolist(),
                    "along_resid_rms_cm": round(float(100 * np.sqrt((along ** 2).mean())), 2),
                    "step_resid_rms_cm": round(float(100 * np.sqrt((step_resid ** 2).mean())), 2),
                    "step_resid_lag1_corr": round(lag1, 2)}
    print(f"track: steps {steps.min():.3f}-{steps.max():.3f} m/frame; centres vs a degree-5 fit RMS (x, y, z) "
          f"{out['track']['position_resid_rms_cm']} cm, along-track {out['track']['along_resid_rms_cm']} cm; step "
          f"lengths vs a smooth fit RMS {out['track']['step_resid_rms_cm']} cm (lag-1 correlation {lag1:.2f}: "
          f"-0.5 would be alternating frames)", flush=True)
    return out


ROAD_ROW = 215  # road matches: below this image row (the horizon is near row 185)


def road_scale(images, feats, poses, k: np.ndarray) -> dict:
    """Map-independent along-track check: per consecutive pair, the road's plane-induced homography
    H = K (R + a n^T) K^-1 fitted to SIFT matches below ROAD_ROW (RANSAC inliers) with R the recorded relative
    rotation; |a| = step / camera height. Its ratio to the recorded step, over the drive: a camera height that
    changes slowly makes it smooth; a per-frame timing or along-track error of e cm makes it jump by ~e / step."""
    from scipy.optimize import least_squares

    kinv = np.linalg.inv(k)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    rows = []
    for i in range(len(images) - 1):
        p1, p2 = ratio_matches(feats[i], feats[i + 1], matcher)
        low = (p1[:, 1] > ROAD_ROW) & (p2[:, 1] > ROAD_ROW)
        p1, p2 = p1[low], p2[low]
        if len(p1) < 12:
            continue
        _, inl = cv2.findHomography(p1, p2, cv2.RANSAC, 1.5)
        inl = inl.ravel() > 0
        p1, p2 = p1[inl], p2[inl]
        if len(p1) < 10:
            continue
        r_rec, t_rec = relative(poses[i], poses[i + 1])
        h0 = 1.65

        def resid(x, p1=p1, p2=p2, r_rec=r_rec):
            a = x[:3]
            # the road's unit normal in camera 1's axes, towards the road (y down): (0, 1, 0) for a level road;
            # its points X satisfy n.X = camera height, so X2 = R X1 + t = (R + t n^T / height) X1
            n = np.array([np.sin(x[3]), np.cos(x[3]) * np.cos(x[4]), np.cos(x[3]) * np.sin(x[4])])
            h = k @ (r_rec + np.outer(a, n)) @ kinv
            q = np.c_[p1, np.ones(len(p1))] @ h.T
            return (q[:, :2] / q[:, 2:3] - p2).ravel()

        fit = least_squares(resid, np.r_[t_rec / h0, 0.0, 0.0], loss="soft_l1", f_scale=0.5)
        a = fit.x[:3]
        rms = float(np.sqrt(np.mean(fit.fun ** 2)))
        height = float(np.linalg.norm(t_rec) / np.linalg.norm(a))
        if not 1.3 < height < 2.2:  # a degenerate fit (another plane, or too few spread road points): dropped
            print(f"  {i:2d}->{i + 1:2d}: road plane fit degenerate (height {height:.2f} m), dropped")
            continue
        rows.append({"frame": i, "matches": int(len(p1)), "ratio": float(np.linalg.norm(a) / np.linalg.norm(t_rec)),
                     "height_m": height, "rms_px": rms})
    ratio = np.array([r["ratio"] for r in rows])
    frames = np.array([r["frame"] for r in rows])
    smooth = np.polyval(np.polyfit(frames, ratio, 3), frames)
    dev = ratio / smooth - 1
    lag1 = float(np.corrcoef(dev[:-1], dev[1:])[0, 1])
    steps = np.array([np.linalg.norm(relative(poses[f], poses[f + 1])[1]) for f in frames])
    # a per-frame along-track error e_k changes step k by e_{k+1} - e_k: consecutive steps' ratios jump by
    # about that; the ratios' frame-to-frame differences bound it (measurement noise included)
    jump = np.diff(dev) * steps[1:]
    print(f"  step ratio frame-to-frame jumps: RMS {100 * np.sqrt(np.mean(jump ** 2)):.2f} cm, median "
          f"|jump| {100 * np.median(np.abs(jump)):.2f} cm")
    print(f"road homography (known rotation): {len(rows)} pairs, {np.median([r['matches'] for r in rows]):.0f} road "
          f"matches median, reprojection RMS {np.median([r['rms_px'] for r in rows]):.2f} px; camera height implied by "
          f"the recorded steps {np.median([r['height_m'] for r in rows]):.3f} m (range "
          f"{min(r['height_m'] for r in rows):.3f}-{max(r['height_m'] for r in rows):.3f}); step ratio vs a smooth fit "
          f"{100 * dev.std():.2f} % RMS = {100 * float(np.sqrt(np.mean((dev * steps) ** 2))):.2f} cm a step, lag-1 "
          f"correlation {lag1:.2f}", flush=True)
    for r, d in zip(rows, dev, strict=True):
        print(f"  {r['frame']:2d}->{r['frame'] + 1:2d}: {r['matches']:3d} road matches, height {r['height_m']:.3f} m, "
              f"step ratio {100 * d:+.2f} % of smooth, {r['rms_px']:.2f} px")
    return {"pairs": len(rows), "height_median_m": round(float(np.median([r["height_m"] for r in rows])), 3),
            "step_ratio_dev_rms_pct": round(float(100 * dev.std()), 2),
            "step_dev_rms_cm": round(100 * float(np.sqrt(np.mean((dev * steps) ** 2))), 2),
            "step_dev_lag1_corr": round(lag1, 2),
            "step_jump_rms_cm": round(100 * float(np.sqrt(np.mean(jump ** 2))), 2),
            "step_jump_median_abs_cm": round(100 * float(np.median(np.abs(jump))), 2)}


def epipolar_of_corrections(rows: list[dict], key: str = "searched") -> dict:
    """Would the views' rigid corrections (fitted against the map) make the raw frames' SIFT matches agree better
    with the poses? Per corrected view k: the median Sampson error (px) of the matches of frames k-1 -> k and
    k -> k+1 under the recorded poses and with frame k's pose corrected. A real pose error of frame k lowers it."""
    poses, k = recorded_poses_and_k()
    kinv = np.linalg.inv(k)
    files = sorted((FOLDER / "image_0").glob("*.png"))
    sift = cv2.SIFT_create(nfeatures=4000)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    cache = {}

    def feats(i):
        if i not in cache:
            cache[i] = sift.detectAndCompute(cv2.imread(str(files[i]), cv2.IMREAD_GRAYSCALE), None)
        return cache[i]

    def median_sampson(a, b, pa, pb):
        p1, p2, _ = inlier_matches(feats(a), feats(b), k, matcher)
        r, t = relative(pa, pb)
        return float(np.median(sampson(kinv.T @ skew(t) @ r @ kinv, p1, p2)))

    out = []
    for row in rows:
        f = row["frame"]
        c = row[key]
        p = np.array([np.radians(c["pitch_deg"]) * 1e3, np.radians(c["yaw_deg"]) * 1e3,
                      np.radians(c["roll_deg"]) * 1e3, c["lateral_cm"], c["down_cm"], c["along_cm"]])
        fixed = poses[f] @ correction_matrix(p)
        before, after = [], []
        for a, b in ((f - 1, f), (f, f + 1)):
            if 0 <= a and b < len(poses):
                before.append(median_sampson(a, b, poses[a], poses[b]))
                after.append(median_sampson(a, b, fixed if a == f else poses[a], fixed if b == f else poses[b]))
        out.append({"kind": row["kind"], "frame": f, "sampson_recorded_px": round(float(np.mean(before)), 3),
                    "sampson_corrected_px": round(float(np.mean(after)), 3)})
        print(f"  {row['kind']:5s} frame {f:2d}: neighbours' Sampson median {np.mean(before):.3f} px with the recorded "
              f"pose, {np.mean(after):.3f} px with the map-fitted ({key}) correction", flush=True)
    return {"views": out, "recorded_mean_px": round(float(np.mean([o["sampson_recorded_px"] for o in out])), 3),
            "corrected_mean_px": round(float(np.mean([o["sampson_corrected_px"] for o in out])), 3)}
