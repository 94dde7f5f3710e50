"""The evaluation report as a plain-text table (what `reloc evaluate` and `reloc demo` print)."""

from __future__ import annotations

from pathlib import Path


def _f(v: float | None, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


def _pose_row(name: str, s: dict) -> str:
    return (f"  {name:<28} {_f(s['median_t_m'], '8.3f')} m {_f(s['median_r_deg'], '7.2f')} deg "
            f"{_f(s['pct_5cm_5deg'], '8.1f')} % {_f(s.get('pct_10cm_5deg'), '9.1f')} % "
            f"{_f(s['pct_10cm_10deg'], '9.1f')} %")


def _depth_row(name: str, d: dict) -> str:
    return (f"  {name:<20}" + "".join(
        f"{d[k]:>9.3f}" for k in ("abs_rel", "sq_rel", "rmse", "rmse_log", "delta1", "delta2", "delta3"))
        + f"{d['scale_std_over_median']:>11.3f}")


def format_table(report: dict) -> str:
    """A human-readable summary of a report (schema ``report``)."""
    pose, base, ds = report["pose"], report["baselines"], report["dataset"]
    lines = [
        (f"evaluation of {report['checkpoint']['path']} (step {report['checkpoint']['step']}"
         f"{', averaged weights' if report['checkpoint'].get('weights') == 'average' else ''}) "
        f"on {ds['path']}: {ds['train_frames']} train / {ds['test_frames']} test frames"),
        "",
        f"pose, test frames, Sim(3) fitted on train (scale {report['alignment']['scale']:.4g})",
        (f"  {'':<28} {'median t':>10} {'median r':>11} {'5cm/5deg':>10} {'10cm/5deg':>11} "
         f"{'10cm/10deg':>11}"),
        _pose_row("relocdepth", pose["test"]),
    ]
    align = report["alignment"]
    if align.get("degenerate"):  # older reports lack the field
        lines.insert(3, f"warning: the Sim(3) fit is degenerate: {align['degenerate_reason']}; the "
                        "aligned errors below mean nothing (the rotation-only alignment still does)")
    if len(pose["per_sequence"]) > 1:
        lines += [_pose_row(f"  {seq}", s) for seq, s in pose["per_sequence"].items()]
    if "refined" in pose:  # evaluate --refine
        lines.append(_pose_row("refined, nearest train", pose["refined"]["test"]))
    lines += [
        _pose_row("mean training pose", base["mean_pose"]),
        _pose_row("thumbnail retrieval", base["retrieval"]),
    ]
    if "nearest_training_centre" in base:  # older reports lack it
        lines.append(_pose_row("nearest train centre, oracle", base["nearest_training_centre"]))
    lines += [
        _pose_row("(train frames, fit residual)", pose["train"]),
        "",
        f"rotation-only alignment: median rotation error {pose['rotation_only']['median_r_deg']:.2f} deg"
        + (f"; it is {pose['rotation_only']['fit_gap_deg']:.2f} deg from the centre-fitted Sim(3)'s rotation"
           if "fit_gap_deg" in pose["rotation_only"] else ""),  # older reports lack it
    ]
    if "refined" in pose:
        ref = pose["refined"]
        lines.append(
            f"refined against the {ref['neighbours']} nearest training frames"
            + (f" (the map: the run's {'anchors' if ref['map'] == 'anchors' else 'network poses'})" if "map" in ref else "")
            + ": rotation-only "
            f"{ref['rotation_only']['median_r_deg']:.2f} deg; "
            + (f"{ref['aligned']} test frame(s) placed by direct alignment, " if "aligned" in ref else "")
            + f"{ref['network_pose_kept']} kept the network's pose"
        )
        if ref["relative"].get("pairs"):
            lines.append(f"  refined relative pose, frames {ref['relative']['k']} apart: "
                         f"{ref['relative']['median_t_m']:.3f} m {ref['relative']['median_r_deg']:.2f} deg")
    rel = pose["relative"]
    if rel["pairs"]:
        lines.append(
            f"relative pose, frames {rel['k']} apart ({rel['pairs']} pairs): "
            f"{rel['median_t_m']:.3f} m {rel['median_r_deg']:.2f} deg "
            f"(identity: {rel['identity_median_t_m']:.3f} m {rel['identity_median_r_deg']:.2f} deg)"
        )
    if "along_axis" in pose:  # older reports lack it
        ax = pose["along_axis"]
        lines.append(f"test centres along their optical axes: median {ax['median_m']:+.3f} m "
                     f"(|.| {ax['median_abs_m']:.3f} m; + = in front of the true camera)")
    sp = pose["spread"]
    lines.append(
        f"spread of test poses: centres {sp['prediction_aligned']['centre_rms']:.3f} m aligned "
        f"({sp['prediction_raw']['centre_rms']:.3g} raw) vs GT {sp['ground_truth']['centre_rms']:.3f} m; "
        f"rotations {sp['prediction_raw']['rot_median_deg']:.1f} deg vs GT "
        f"{sp['ground_truth']['rot_median_deg']:.1f} deg"
    )
    conf = report.get("confidence")
    if conf:
        lines.append(
            f"confidence (median {_f(conf['median'], '.3f')}) vs error, Spearman: translation "
            f"{_f(conf['spearman_t'], '+.2f')}, rotation {_f(conf['spearman_r'], '+.2f')} "
            "(negative = confidence ranks errors; -1 perfect, 0 not at all)"
        )
    depth = report.get("depth")
    if depth:
        lines += [
            "",
            (f"depth, test frames ({depth['prediction']['frames']}), per-frame median scaling, "
            f"{report['config']['depth_range'][0]:g}-{report['config']['depth_range'][1]:g} m"),
            f"  {'':<20}" + "".join(f"{h:>9}" for h in
                                   ("AbsRel", "SqRel", "RMSE", "RMSElog", "d<1.25", "d<1.25^2", "d<1.25^3"))
            + f"{'scale s/m':>11}",
            _depth_row("relocdepth", depth["prediction"]),
            _depth_row("constant depth", depth["constant_reference"]),
        ]
        units = depth.get("pose_units")  # older reports lack it
        if units:
            train = units.get("train_median")
            lines.append(
                f"  depth in the poses' units (scale / Sim(3) scale): test median {units['median']:.3f}, "
                f"10-90 % {units['p10']:.3f}-{units['p90']:.3f}"
                + (f"; training frames {train:.3f} (test above it = depth shorter on the test views, "
                   "their centres put forward)" if train is not None else ""))
    out = report.get("outputs", {})
    if out:
        lines += ["", f"report: {out.get('report')}"]
        lines += [f"plot: {p}" for p in out.get("plots", [])]
        if out.get("frames_csv"):
            lines.append(f"per-frame errors (CSV): {out['frames_csv']}")
        if out.get("tum"):
            first = next(iter(out["tum"].values()))
            lines.append(f"trajectories (TUM, for evo_ape): {Path(first['estimate']).parent}")
    return "\n".join(lines)

