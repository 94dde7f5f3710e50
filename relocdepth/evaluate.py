"""The paper's evaluation protocol on shards with ground truth (Sec. IV, Tables I-II, Fig. 5).

Pose: predict every training and test frame; fit a Sim(3) (Umeyama, with scale) from the
training predictions' camera centres to the training ground truth; apply it to the test
predictions (the report flags the fit as degenerate when the centres cannot determine it:
too few, coincident or collinear); report median errors and the share within 5 cm/5 deg and
10 cm/10 deg (and 10 cm/5 deg, ACE's and DSAC*'s threshold), per test sequence and overall;
per-frame errors with each frame's confidence go to a CSV, and the report says how well
confidence ranks the errors. Depth: per-frame median scaling over 0.1-10 m (Table II).
For context, on the same split: the mean-training-pose and thumbnail-retrieval baselines, the
constant-depth reference, and the diagnostics of DESIGN.md's Pitfalls (rotation-only
alignment, relative pose vs identity, raw spread of the predictions).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from relocdepth import eval_geometry as EG
from relocdepth import metrics as M
from relocdepth.errors import UserError
from relocdepth.trajectory import sim3_to_dict

if TYPE_CHECKING:
    from relocdepth.refine import Refined, RefineConfig

log = logging.getLogger(__name__)

REPORT_FORMAT = "relocdepth-report"
REPORT_VERSION = 1
MIN_FIT_FRAMES = EG.MIN_ALIGN_POSES  # Umeyama needs three non-collinear centres


@dataclass(frozen=True)
class EvalConfig:
    """Options of ``reloc evaluate``."""

    batch_size: int = 16
    depth_range: tuple[float, float] = M.DEPTH_RANGE  # Table II / monodepth2: 0.1-10 m
    relative_k: int = 5  # relative pose between frames this far apart (the quality table)
    strip_frames: int = 6  # rows of the image | depth | GT plot
    device: str = "auto"  # auto | cpu | cuda | cuda:N
    # Sequences to test on instead of the shards' test split (the rest fit the Sim(3)): e.g. a
    # training sequence, to tell "not learned" from "learned but does not generalise".
    test_sequences: tuple[str, ...] = ()
    # Also refine each test pose against its nearest training frames (relocdepth.refine): the
    # report gains pose.refined and the frames CSV the refined errors. Off: the paper's protocol.
    refine: bool = False
    refine_neighbours: int = 3
    refine_min_pairs: int = 2
    refine_matcher: str = "klt+sift"
    refine_align: bool = True
    # the map's poses (relocdepth.refine.MAPS): the run's anchors when it has them, or the network's
    refine_map: str = "auto"

    def refine_config(self) -> RefineConfig | None:
        """The refinement's config when ``refine`` is on (a bad option: :class:`UserError`)."""
        from relocdepth.refine import MAPS, RefineConfig

        if self.refine and self.refine_map not in MAPS:
            raise UserError(f"unknown --refine-map {self.refine_map!r}; use one of {', '.join(MAPS)}")
        return RefineConfig.from_options(self.refine_neighbours, self.refine_min_pairs,
                                         self.refine_matcher, self.refine_align) if self.refine else None


@dataclass
class Gathered:
    """Predictions and ground truth of one split, in index order."""

    keys: list[str] = field(default_factory=list)
    sequences: list[str] = field(default_factory=list)
    frames: list[int] = field(default_factory=list)
    timestamps: list[float] = field(default_factory=list)
    T_est: list[np.ndarray] = field(default_factory=list)  # raw, networks' frame
    T_gt: list[np.ndarray] = field(default_factory=list)
    thumbs: list[np.ndarray] = field(default_factory=list)
    confidence: list[float] = field(default_factory=list)
    depth: list[dict | None] = field(default_factory=list)  # per-frame depth errors (None: no GT depth)
    constant: list[dict | None] = field(default_factory=list)  # constant-depth reference
    strips: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=list)

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        return np.stack(self.T_est), np.stack(self.T_gt)


# ----------------------------------------------------------------------------- the protocol


def fit_sim3(T_est: np.ndarray, T_gt: np.ndarray) -> EG.Sim3:
    """Sim(3) taking predicted camera centres to GT centres (Umeyama, with scale);
    its ``degenerate`` says when the centres cannot determine it (e.g. collapsed predictions)."""
    return EG.umeyama(T_est[:, :3, 3], T_gt[:, :3, 3], with_scale=True,
                      names=("predicted", "ground-truth"))


def pose_report(
    train_est: np.ndarray, train_gt: np.ndarray, test_est: np.ndarray, test_gt: np.ndarray,
    test_sequences: list[str], relative_k: int = 5,
) -> tuple[dict, EG.Sim3, np.ndarray]:
    """Pose figures of the protocol from raw predictions; returns (report, sim3, aligned test)."""
    fit = fit_sim3(train_est, train_gt)
    train_al = EG.apply_sim3(fit.scale, fit.R, fit.t, train_est)
    test_al = EG.apply_sim3(fit.scale, fit.R, fit.t, test_est)
    t_err, r_err = EG.pose_errors(test_al, test_gt)
    rot_only = EG.rotation_only_errors(
        train_est[:, :3, :3], train_gt[:, :3, :3], test_est[:, :3, :3], test_gt[:, :3, :3]
    )
    report = {
        "test": M.pose_summary(t_err, r_err),
        "per_sequence": M.pose_summary_by_sequence(t_err, r_err, test_sequences),
        "train": M.pose_summary(*EG.pose_errors(train_al, train_gt)),
        "rotation_only": {"median_r_deg": float(np.median(rot_only)), "mean_r_deg": float(np.mean(rot_only))},
        "relative": M.relative_pose_errors(test_al, test_gt, test_sequences, relative_k),
        "along_axis": along_axis_summary(along_axis_errors(test_al, test_gt)),
        "spread": {
            "prediction_raw": EG.pose_spread(test_est),
            "prediction_aligned": EG.pose_spread(test_al),
            "ground_truth": EG.pose_spread(test_gt),
        },
    }
    if fit.degenerate is None:  # a degenerate fit's rotation is arbitrary: no gap to speak of
        report["rotation_only"]["fit_gap_deg"] = alignment_gap_deg(
            fit.R, train_est[:, :3, :3], train_gt[:, :3, :3])
    return report, fit, test_al


def along_axis_errors(T_est: np.ndarray, T_gt: np.ndarray) -> np.ndarray:
    """Signed error (m) of each estimated centre along its true camera's optical axis:
    ``(c_est - c_gt) . R_gt e_z``. Positive = the estimate stands in front of the true camera,
    towards what it sees, as a depth that is too short on that frame puts it (``c = tau - |Q| G e_z``)."""
    T_est, T_gt = np.asarray(T_est, np.float64), np.asarray(T_gt, np.float64)
    return np.einsum("ni,ni->n", T_est[:, :3, 3] - T_gt[:, :3, 3], T_gt[:, :3, 2])


def along_axis_summary(along: np.ndarray) -> dict:
    return {"median_m": float(np.median(along)), "mean_m": float(np.mean(along)),
            "median_abs_m": float(np.median(np.abs(along)))}


def depth_pose_ratios(per_frame: list[dict | None], alignment_scale: float) -> np.ndarray:
    """Per frame, how far the network's depth is from its own poses' units: the frame's median
    scaling factor (ground truth over prediction, metres per depth unit) over the Sim(3)'s scale
    (metres per pose unit); NaN where a frame has no depth. 1 = the depth is in the units of the
    poses; 1.1 = 10 % too short there, which moves the camera's centre forward along its axis."""
    return np.array([np.nan if f is None else f["scale"] / alignment_scale for f in per_frame], np.float64)


def depth_pose_summary(ratios: np.ndarray, train_ratios: np.ndarray | None = None) -> dict | None:
    """Median and 10-90 % of the test frames' ratios, beside the training frames' median (the
    units the poses were fitted in: a test median away from it is depth that did not carry over
    to the test views; None when no training frame has depth)."""
    r = ratios[np.isfinite(ratios)]
    if r.size == 0:
        return None
    p10, p50, p90 = np.percentile(r, [10, 50, 90])
    tr = np.asarray([] if train_ratios is None else train_ratios, np.float64)
    tr = tr[np.isfinite(tr)]
    return {"frames": int(r.size), "median": float(p50), "p10": float(p10), "p90": float(p90),
            "train_median": float(np.median(tr)) if tr.size else None}


def alignment_gap_deg(R_sim3: np.ndarray, R_est: np.ndarray, R_gt: np.ndarray) -> float:
    """How far (deg) the Sim(3) fitted on the camera centres turns the world from the rotation
    fitted on the orientations (both on the same frames). 0 when the predicted centres and
    orientations are one rigid world; when not, every aligned rotation inherits this gap, however
    right the orientations are among themselves (README, trial 18)."""
    A = EG.rotation_alignment(R_est, R_gt)
    return float(EG.rotation_angle_deg(A @ np.asarray(R_sim3, np.float64).T))


def baselines_report(
    train_gt: np.ndarray, test_gt: np.ndarray, train_thumbs: np.ndarray, test_thumbs: np.ndarray
) -> dict:
    """The mean-training-pose and thumbnail-retrieval baselines on the test frames, and the
    nearest-training-centre oracle (how far the test cameras stand from the training ones)."""
    mean = M.mean_pose_baseline(train_gt, len(test_gt))
    retrieved, _ = M.retrieval_baseline(train_thumbs, train_gt, test_thumbs)
    nearest, _, _ = M.nearest_centre_baseline(train_gt, test_gt)
    return {
        "mean_pose": M.pose_summary(*EG.pose_errors(mean, test_gt)),
        "retrieval": M.pose_summary(*EG.pose_errors(retrieved, test_gt)),
        "nearest_training_centre": M.pose_summary(*EG.pose_errors(nearest, test_gt)),
    }


# ----------------------------------------------------------------------------- gathering


def _checked_records(ds, test_sequences: tuple[str, ...] = ()) -> tuple[list, list]:
    posed = [r for r in ds.records if r.has_pose]
    if not posed:
        raise UserError(
            f"{ds.root} has no ground-truth poses; evaluate needs shards ingested from a source "
            "with poses (e.g. a 7-Scenes folder or `reloc synth`)"
        )
    if test_sequences:
        known = list(dict.fromkeys(r.sequence for r in posed))
        unknown = [name for name in test_sequences if name not in known]
        if unknown:
            raise UserError(f"no sequence {', '.join(unknown)} with poses in {ds.root} "
                            f"(it has {', '.join(known)})")
    # the Sim(3) comes from the training split only, the named sequences left out: frames the
    # networks never saw (the test split's) would pull it towards their own errors
    train = [r for r in posed if r.split == "train" and r.sequence not in test_sequences]
    test = [r for r in posed if (r.sequence in test_sequences if test_sequences else r.split == "test")]
    if len(train) < MIN_FIT_FRAMES:
        outside = f" outside {', '.join(test_sequences)}" if test_sequences else ""
        raise UserError(f"{ds.root} has {len(train)} training frames with poses{outside}; the Sim(3) fit "
                        f"needs at least {MIN_FIT_FRAMES}")
    if not test:
        raise UserError(f"{ds.root} has no test frames with poses (the test split is empty)")
    return train, test


def _strip_indices(records: list, n: int) -> set[int]:
    with_depth = [i for i, r in enumerate(records) if r.has_depth]
    if not with_depth or n <= 0:
        return set()
    pick = np.linspace(0, len(with_depth) - 1, min(n, len(with_depth))).round().astype(int)
    return {with_depth[i] for i in pick}


def _depth_errors(pred: np.ndarray, gt: np.ndarray, cfg: EvalConfig) -> dict | None:
    """One frame's depth errors: the prediction resized to the ground truth's map."""
    import cv2

    d = cv2.resize(pred, (gt.shape[1], gt.shape[0]), interpolation=cv2.INTER_LINEAR)
    return M.depth_errors(d, gt, cfg.depth_range)


SCALE_FRAMES = 300  # training frames whose depth scale is measured (the median of them is reported)


def gather(ds, predictor, records: list, cfg: EvalConfig, depth: bool, label: str,
           depth_scales: bool = False) -> Gathered:
    """Predict ``records`` in batches; collect GT, thumbnails and (optionally) depth errors, or
    with ``depth_scales`` the depth errors of up to ``SCALE_FRAMES`` of them, for their scaling factor
    (None for the others and where there is no ground-truth depth)."""
    from relocdepth.progress import progress_bar

    g = Gathered()
    strips = _strip_indices(records, cfg.strip_frames) if depth else set()
    with progress_bar("evaluate", "frames") as progress:
        task = progress.add_task(f"predict {label}", total=len(records))
        for start in range(0, len(records), cfg.batch_size):
            recs = records[start:start + cfg.batch_size]
            imgs = [ds.read_image(r) for r in recs]
            pred = predictor.predict(imgs, [r.intrinsics for r in recs], with_depth=depth or depth_scales)
            for i, (rec, img) in enumerate(zip(recs, imgs)):
                g.keys.append(rec.key)
                g.sequences.append(rec.sequence)
                g.frames.append(int(rec.frame))
                g.timestamps.append(rec.timestamp)
                g.T_est.append(pred.T_wc[i])
                g.T_gt.append(ds.read_pose(rec))
                g.thumbs.append(M.thumbnail(img))
                g.confidence.append(float(pred.confidence[i]))
                if depth and rec.has_depth:
                    gt = ds.read_depth(rec)
                    g.depth.append(_depth_errors(pred.depth[i], gt, cfg))
                    g.constant.append(M.constant_depth_errors(gt, cfg.depth_range))
                    if start + i in strips:
                        g.strips.append((img, pred.depth[i], gt))
                elif depth:  # one entry per frame, so that per-frame columns line up
                    g.depth.append(None)
                    g.constant.append(None)
                elif depth_scales:  # at most ~SCALE_FRAMES of them, evenly spread
                    take = rec.has_depth and (start + i) % max(1, len(records) // SCALE_FRAMES) == 0
                    g.depth.append(_depth_errors(pred.depth[i], ds.read_depth(rec), cfg) if take else None)
            progress.advance(task, len(recs))
    return g


# ----------------------------------------------------------------------------- the job


def evaluate(
    shards: str | Path, checkpoint: str | Path | None, cfg: EvalConfig,
    report_path: str | Path | None = None, plots_dir: str | Path | None = None,
    save_alignment: bool = False,
) -> dict:
    """The ``reloc evaluate`` job; returns the report (schema ``report``) after writing it.

    Outputs: ``report_path`` (default ``<run>/eval/report.json``), the per-frame errors beside it
    (``<report stem>.frames.csv``: sequence, frame, t_err_m, r_err_deg, confidence), TUM files of the aligned
    estimate and the GT per test sequence in ``<report dir>/trajectories/``, and PNG plots in
    ``plots_dir`` (default ``<report dir>/plots/``).
    """
    from relocdepth.checkpoint import save_alignment as store_alignment
    from relocdepth.dataset import open_dataset
    from relocdepth.distributed import pick_device
    from relocdepth.fileio import write_text_atomic
    from relocdepth.predictor import Predictor
    from relocdepth.schemas import validate

    refine = cfg.refine_config()  # checked before any work
    ds = open_dataset(shards)
    train_recs, test_recs = _checked_records(ds, cfg.test_sequences)
    predictor = Predictor.from_checkpoint(checkpoint, device=str(pick_device(cfg.device)))
    ckpt_path = Path(predictor.meta["path"])
    report_path = Path(report_path) if report_path else ckpt_path.parent.parent / "eval" / "report.json"
    if report_path.is_dir():
        raise UserError(f"-o {report_path} is a folder; give a file name such as report.json")
    plots = Path(plots_dir) if plots_dir else report_path.parent / "plots"
    if predictor.meta.get("manifest_hash") != ds.manifest_hash:
        log.warning("the checkpoint was trained on other shards than %s", ds.root)
    from relocdepth.refine import map_anchors

    keys = [r.key for r in train_recs]
    # the run's anchors of these training frames (None: it has none); as the refinement's map
    # only where --refine-map takes them (asked for and missing: refused before any work)
    run_anchors = map_anchors("auto", predictor.meta, ds, keys)
    anchors = None if refine is None else map_anchors(cfg.refine_map, predictor.meta, ds, keys)

    tr = gather(ds, predictor, train_recs, cfg, depth=False, label="train", depth_scales=True)
    te = gather(ds, predictor, test_recs, cfg, depth=True, label="test")
    train_est, train_gt = tr.arrays()
    test_est, test_gt = te.arrays()
    pose, fit, test_al = pose_report(
        train_est, train_gt, test_est, test_gt, te.sequences, cfg.relative_k
    )
    created = datetime.now(timezone.utc).isoformat(timespec="seconds")
    alignment = sim3_to_dict(fit.scale, fit.R, fit.t, fitted_on=str(ds.root),
                             frames=len(train_recs), manifest_hash=ds.manifest_hash, created=created,
                             degenerate=fit.degenerate is not None, degenerate_reason=fit.degenerate)
    anchors_fit = None if run_anchors is None else fit_sim3(run_anchors, train_gt)
    if anchors_fit is not None:  # for poses refined against the anchors (here, and localize's)
        alignment["anchors"] = sim3_to_dict(anchors_fit.scale, anchors_fit.R, anchors_fit.t,
                                            frames=len(train_recs), degenerate=anchors_fit.degenerate is not None,
                                            degenerate_reason=anchors_fit.degenerate)
    depth = M.depth_summary(te.depth)
    units = depth is not None and fit.degenerate is None
    ratios = depth_pose_ratios(te.depth, fit.scale) if units else np.full(len(test_recs), np.nan)
    train_ratios = depth_pose_ratios(tr.depth, fit.scale) if units else None
    t_err, r_err = EG.pose_errors(test_al, test_gt)
    refined = None
    if refine is not None:
        map_T, map_fit, map_name = (train_est, fit, "network") if anchors is None else (anchors, anchors_fit, "anchors")
        results = refine_test_poses(ds, predictor, train_recs, test_recs, map_T, test_est, refine)
        pose["refined"], refined_al = refined_report(map_fit, map_T, train_gt, results, test_gt,
                                                     te.sequences, refine, cfg.relative_k, network_fit=fit)
        pose["refined"]["map"] = map_name
        refined = (*EG.pose_errors(refined_al, test_gt), results)
    report = {
        "format": REPORT_FORMAT, "schema_version": REPORT_VERSION,
        "tool_version": _tool_version(), "created": created,
        "dataset": {"path": str(ds.root), "manifest_hash": ds.manifest_hash,
                    "train_frames": len(train_recs), "test_frames": len(test_recs),
                    "test_sequences": list(dict.fromkeys(te.sequences))},
        "checkpoint": {"path": str(ckpt_path), "step": int(predictor.meta.get("step", 0)),
                       "input_size": list(predictor.input_size), "weights": predictor.meta.get("weights", "raw"),
                       "same_data": predictor.meta.get("manifest_hash") == ds.manifest_hash},
        "config": _jsonable(asdict(cfg)),
        "alignment": alignment | {"rotation_only_fit": "train rotations"},
        "pose": pose,
        "baselines": baselines_report(train_gt, test_gt, np.stack(tr.thumbs), np.stack(te.thumbs)),
        "depth": None if depth is None else {
            "prediction": depth, "constant_reference": M.depth_summary(te.constant),
            "pose_units": depth_pose_summary(ratios, train_ratios)},
        "confidence_median": float(np.median(te.confidence)),
        "confidence": M.confidence_ranking(np.asarray(te.confidence), t_err, r_err),
        "saved_alignment": bool(save_alignment),
        "outputs": {},
    }
    report["outputs"] = _write_outputs(report_path, plots, te, test_al, test_gt, train_gt, pose)
    frames_csv = frames_csv_path(report_path)
    nearest_m = M.nearest_centre_baseline(train_gt, test_gt)[2]
    write_text_atomic(frames_csv, per_frame_csv(te, t_err, r_err, nearest_m,
                                                along_axis_errors(test_al, test_gt), ratios, refined))
    report["outputs"]["frames_csv"] = str(frames_csv)
    validate("report", report, what="evaluation report")
    write_text_atomic(report_path, _dumps(report))
    if save_alignment:
        store_alignment(ckpt_path, alignment)
    return report


def frames_csv_path(report_path: Path) -> Path:
    """Where the per-frame errors of a report go: ``report.json`` -> ``report.frames.csv``."""
    return report_path.with_name(report_path.stem + ".frames.csv")


FRAMES_CSV_HEADER = ("sequence", "frame", "t_err_m", "r_err_deg", "confidence", "nearest_train_m",
                     "along_axis_m", "depth_pose_ratio")
FRAMES_CSV_REFINED = ("refined_t_err_m", "refined_r_err_deg", "refined_pairs", "refined_by")


def per_frame_csv(te: Gathered, t_err: np.ndarray, r_err: np.ndarray, nearest_m: np.ndarray,
                  along_m: np.ndarray, depth_ratio: np.ndarray,
                  refined: tuple[np.ndarray, np.ndarray, list[Refined]] | None = None) -> str:
    """CSV text: one row per test frame (errors after the Sim(3), the frame's confidence, the
    distance from its true camera centre to the nearest training frame's, the error along its
    optical axis and its depth's ratio to the poses' units, empty without depth); with ``refined``
    (t_err, r_err, the refinements: pairs agreeing, what placed it) the refined pose's errors too."""
    import csv
    import io

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(FRAMES_CSV_HEADER + (FRAMES_CSV_REFINED if refined is not None else ()))
    rows = zip(te.sequences, te.frames, t_err, r_err, te.confidence, nearest_m, along_m, depth_ratio, strict=True)
    for i, (seq, frame, t, r, c, n, a, d) in enumerate(rows):
        row = [seq, frame, f"{t:.6g}", f"{r:.6g}", f"{c:.6g}", f"{n:.6g}",
               "" if not np.isfinite(a) else f"{a:.6g}", "" if not np.isfinite(d) else f"{d:.6g}"]
        if refined is not None:
            row += [f"{refined[0][i]:.6g}", f"{refined[1][i]:.6g}", str(refined[2][i].pairs), refined[2][i].by]
        w.writerow(row)
    return buf.getvalue()


def refine_test_poses(ds, predictor, train_recs: list, test_recs: list, map_T: np.ndarray,
                      test_est: np.ndarray, refine: RefineConfig) -> list[Refined]:
    """Each test pose refined against its nearest training frames (:mod:`relocdepth.refine`;
    ``map_T``: the training frames' poses in the networks' world, the run's anchors or the network's
    own); each :class:`~relocdepth.refine.Refined` in the networks' frame."""
    from relocdepth.progress import progress_bar
    from relocdepth.refine import Refiner

    refiner = Refiner.from_images(predictor, lambda i: ds.read_image(train_recs[i]),
                                  [r.intrinsics for r in train_recs], map_T, refine)
    out = []
    with progress_bar("evaluate", "frames") as progress:
        task = progress.add_task("refine test", total=len(test_recs))
        for rec, T in zip(test_recs, test_est, strict=True):
            out.append(refiner.refine(ds.read_image(rec), rec.intrinsics, T))
            progress.advance(task, 1)
    return out


def refined_report(fit: EG.Sim3, train_est: np.ndarray, train_gt: np.ndarray, results: list[Refined],
                   test_gt: np.ndarray, test_sequences: list[str], refine: RefineConfig,
                   relative_k: int = 5, network_fit: EG.Sim3 | None = None) -> tuple[dict, np.ndarray]:
    """The refined test poses under the alignment ``fit`` of the map's training poses
    ``train_est`` (the network's, or the run's anchors) to ``train_gt``, those that kept the
    network's pose under ``network_fit`` (its own poses' alignment; None: ``fit``); returns
    (report section ``pose.refined``, aligned poses)."""
    from relocdepth.refine import align_refined

    refined = np.stack([r.T_wc for r in results])
    by = [r.by for r in results]
    kept_fit = network_fit or fit
    al = align_refined(results, (fit.scale, fit.R, fit.t), (kept_fit.scale, kept_fit.R, kept_fit.t))
    t_err, r_err = EG.pose_errors(al, test_gt)
    rot_only = EG.rotation_only_errors(train_est[:, :3, :3], train_gt[:, :3, :3], refined[:, :3, :3],
                                       test_gt[:, :3, :3])
    return {
        "test": M.pose_summary(t_err, r_err),
        "per_sequence": M.pose_summary_by_sequence(t_err, r_err, test_sequences),
        "rotation_only": {"median_r_deg": float(np.median(rot_only)), "mean_r_deg": float(np.mean(rot_only))},
        "relative": M.relative_pose_errors(al, test_gt, test_sequences, relative_k),
        "neighbours": refine.neighbours,
        "min_pairs": refine.min_pairs,
        "matcher": refine.matcher,
        "align": refine.align,
        "aligned": by.count("aligned"),
        "network_pose_kept": by.count("none"),
    }, al


def _write_outputs(report_path: Path, plots: Path, te: Gathered, test_al: np.ndarray,
                   test_gt: np.ndarray, train_gt: np.ndarray, pose: dict) -> dict:
    from relocdepth.plots import depth_strips, trajectory_plot
    from relocdepth.trajectory import write_tum

    traj = report_path.parent / "trajectories"
    seqs = np.asarray(te.sequences)
    ts = np.asarray(te.timestamps)
    tum = {}
    gt_by, est_by = {}, {}
    for seq in dict.fromkeys(te.sequences):
        m = seqs == seq
        est_f, gt_f = traj / f"{seq}.estimate.tum", traj / f"{seq}.groundtruth.tum"
        write_tum(est_f, ts[m], test_al[m])
        write_tum(gt_f, ts[m], test_gt[m])
        tum[seq] = {"estimate": str(est_f), "groundtruth": str(gt_f)}
        gt_by[seq], est_by[seq] = test_gt[m, :3, 3], test_al[m, :3, 3]
    test = pose["test"]
    title = (f"test: median {test['median_t_m']:.3f} m, {test['median_r_deg']:.1f} deg "
             "(Sim(3) fitted on train)")
    traj_png = plots / "trajectory.png"
    trajectory_plot(traj_png, gt_by, est_by, train_gt[:, :3, 3], title)
    out = {"report": str(report_path), "tum": tum, "plots": [str(traj_png)]}
    if te.strips:
        strips_png = plots / "depth_strips.png"
        depth_strips(strips_png, te.strips)
        out["plots"].append(str(strips_png))
    return out


def _tool_version() -> str:
    from relocdepth import __version__

    return __version__


def _jsonable(obj):
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    return obj


def _dumps(obj) -> str:
    import json

    return json.dumps(obj, indent=2) + "\n"
