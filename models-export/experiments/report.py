"""Markdown for docs/RESULTS.md: our ablation beside the paper's Tables 1-3 on the clean profile.
docs/RESULTS.md also holds hand-written sections on the street profiles: merge the output into it
rather than overwrite it.

    python -m experiments.report runs/ablation/results.json --preface docs/results-convention.md \\
        --notes docs/results-analysis.md \\
        --choices docs/results-choices.md --out runs/ablation/RESULTS.md

Without --out the markdown goes to standard output."""

from __future__ import annotations

from posefuse_train.keypoints import PARTS

PAPER_T1 = {  # OKS@3D %, MPJPE cm, OKS@2D %
    "camera-only": (51.74, 13.90, 78.19),
    "LiDAR-only": (59.58, 10.80, 77.53),
    "multi-modal": (63.14, 10.32, 82.94),
}
PAPER_T3 = {
    "lidar_reg": (59.10, 10.93, 77.52),
    "lidar_reg_seg": (59.58, 10.80, 77.53),
    "fusion_reg": (62.03, 10.53, 82.51),
    "fusion_reg_seg": (63.14, 10.32, 82.94),
}
PAPER_T2 = {  # per-keypoint OKS@3D %: camera, LiDAR, multi-modal
    "nose": (24.50, 23.83, 29.74),
    "shoulder": (65.41, 77.04, 76.93),
    "elbow": (65.61, 66.61, 72.49),
    "wrist": (45.99, 30.37, 46.97),
    "hip": (57.69, 79.42, 74.76),
    "knee": (65.40, 77.48, 78.04),
    "ankle": (62.68, 69.06, 72.30),
}
PAPER_T2_2D = {  # per-keypoint OKS@2D % (the internal test set): camera, LiDAR, multi-modal
    "nose": (75.10, 56.27, 72.17),
    "shoulder": (83.38, 85.68, 87.89),
    "elbow": (82.63, 78.72, 84.82),
    "wrist": (79.03, 64.10, 79.17),
    "hip": (87.97, 90.33, 92.37),
    "knee": (85.91, 86.82, 90.05),
    "ankle": (84.17, 85.63, 88.72),
}
T1_ROWS = (("camera-only", "camera"), ("LiDAR-only", "lidar_reg_seg"), ("multi-modal", "fusion_reg_seg"))


def pct(v):
    return "-" if v is None else f"{100 * v:.2f}%"


def cm(v):
    return "-" if v is None else f"{100 * v:.2f} cm"


def md_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def part_oks(report: dict, part: str, key: str = "per_keypoint_oks_3d"):
    """Mean OKS of a part's keypoints (left and right weigh equally)."""
    vals = [report[key][k]["oks"] for k in PARTS[part]]
    vals = [v for v in vals if v is not None]
    return sum(vals) / len(vals) if vals else None


def table1(rows: dict) -> str:
    header = ["method", "OKS@3D", "MPJPE", "OKS@2D", "paper OKS@3D", "paper MPJPE", "paper OKS@2D"]
    body = []
    for label, key in T1_ROWS:
        if key in rows:
            r, p = rows[key]["metrics"], PAPER_T1[label]
            mine = [pct(r["oks_acc_3d"]), cm(r["mpjpe_3d_m"]), pct(r["oks_acc_2d"])]
            body.append([label, *mine, f"{p[0]:.2f}%", f"{p[1]:.2f} cm", f"{p[2]:.2f}%"])
    return md_table(header, body)


def table2(rows: dict) -> str:
    keys = [(label, key, i) for i, (label, key) in enumerate(T1_ROWS) if key in rows]
    header = ["part"]
    for label, _, _ in keys:
        header += [f"{label} OKS@3D", "paper", f"{label} OKS@2D"]
    body = []
    for part in PARTS:
        cells = [part]
        for _, key, i in keys:
            r = rows[key]["metrics"]
            cells += [
                pct(part_oks(r, part)),
                f"{PAPER_T2[part][i]:.2f}%",
                pct(part_oks(r, part, "per_keypoint_oks_2d")),
            ]
        body.append(cells)
    cells = ["overall (OKS/ACC)"]
    for label, key, _ in keys:
        r = rows[key]["metrics"]
        cells += [pct(r["oks_acc_3d"]), f"{PAPER_T1[label][0]:.2f}%", pct(r["oks_acc_2d"])]
    body.append(cells)
    return md_table(header, body)


def table3(rows: dict) -> str:
    header = ["Reg.", "Seg.", "Camera", "labels", "OKS@3D", "MPJPE", "OKS@2D", "PCK@10cm", "PEM"]
    header += ["paper OKS@3D", "paper MPJPE", "paper OKS@2D", "steps", "train time"]
    body = []
    for key, row in rows.items():
        if key == "camera":
            continue
        c, r, p = row["config"], row["metrics"], PAPER_T3.get(key)
        paper = [f"{p[0]:.2f}%", f"{p[1]:.2f} cm", f"{p[2]:.2f}%"] if p else ["-", "-", "-"]
        body.append(
            ["✓", "✓" if c["seg"] else "", "✓" if c["fusion"] else ""]
            + ["eq. 1 + depth correction" if c.get("depth_correction") else "eq. 1"]
            + [pct(r["oks_acc_3d"]), cm(r["mpjpe_3d_m"]), pct(r["oks_acc_2d"]), pct(r["pck_3d_10cm"])]
            + [cm(r["pem_3d_m"]), *paper, str(row.get("steps", "-")), f"{row.get('train_s', 0):.0f} s"]
        )
    table = md_table(header, body)
    # rows added later from their own run (same data, camera checkpoint and step count) say so
    for key, row in rows.items():
        if row.get("separate_run"):
            table += f"\n\nRow `{key}` was trained in a separate run: `{row['separate_run']}`."
    return table


def backbone_table(b: dict) -> str:
    header = ["backbone", "deconv", "params", "train", "PCK2D@0.05S", "PCK2D@0.1S"]
    header += ["camera-only OKS@3D", "camera-only MPJPE", "ORT ms (batch 1)"]
    body = []
    for r in b["rows"]:
        trained = "pck2d_5pct" in r
        body.append(
            [r["backbone"], str(r["deconv_channels"]), f"{r['params_m']:.2f} M"]
            + ([f"{r['epochs']:.1f} ep / {r['train_s']:.0f} s"] if trained else ["not trained"])
            + ([pct(r["pck2d_5pct"]), pct(r["pck2d_10pct"])] if trained else ["-", "-"])
            + ([pct(r["camera_only_oks3d"]), cm(r["camera_only_mpjpe_m"])] if trained else ["-", "-"])
            + [
                f"{r['ort_ms_b1']:.2f}"
                + (f" ({r['ort_ms_b1_at_256']:.1f} at 256²)" if "ort_ms_b1_at_256" in r else "")
            ]
        )
    return md_table(header, body)


def by_range_table(table: list[dict]) -> str:
    rows = [k for k in table[0] if k not in ("range_m", "persons", "mean_points")]
    header = ["range (m)", "persons", "in-box points", *rows]
    body = [
        [c["range_m"], str(c["persons"]), f"{c['mean_points']:.0f}"]
        + [f"{pct(c[r]['oks_acc_3d'])} / {cm(c[r]['mpjpe_3d_m'])}" for r in rows]
        for c in table
    ]
    return md_table(header, body)


def paper_order(rows: dict) -> dict:
    """The paper's Table 3 rows first, in its order, then ours."""
    return {k: rows[k] for k in PAPER_T3 if k in rows} | {k: v for k, v in rows.items() if k not in PAPER_T3}


def point_rows_by(runs: list[dict], key) -> dict:
    """The point-net rows of several runs, grouped by key(row config); a later run's row replaces
    an earlier one of the same name in its group."""
    groups: dict = {}
    for run in runs:
        for name, row in run["rows"].items():
            if name != "camera":
                groups.setdefault(key(row["config"]), {})[name] = row
    return groups


def commands(runs: list[dict]) -> list[str]:
    return ["", "Commands:", "", *[f"- `{s['command']}` ({s['wall_s'] / 60:.1f} min)" for s in runs]]


def paper_recipe_section(runs: list[dict]) -> list[str]:
    """Rows trained with the paper's rotation augmentation ([0, 2π): the box heading is of no use),
    from one or more ablation runs on the same data and camera checkpoint; one table per seed."""
    by_seed = point_rows_by(runs, lambda c: c.get("seed", 0))
    rotations = sorted({v["config"]["rotate_deg"] for rows in by_seed.values() for v in rows.values()})
    lines = [
        "## Table 3 with the paper's rotation augmentation",
        "",
        f"The same rows trained with random rotation ±{'/'.join(f'{r:g}' for r in rotations)}° about z "
        "(the paper: [0, 2π)), so the networks must read the body's facing from the points (and the "
        "camera) instead of from the box heading; same data, camera net and step count as above.",
    ]
    for seed in sorted(by_seed):
        lines += ["", f"Point-net seed {seed}:", "", table3(paper_order(by_seed[seed]))]
    return [*lines, *commands(runs)]


# (what, rows compared as b − a); the paper's differences come from its Tables 2 and 3
STREET_DIFFS = (
    ("multi-modal − LiDAR-only, reg + seg", "lidar_reg_seg", "fusion_reg_seg"),
    ("multi-modal − LiDAR-only, reg", "lidar_reg", "fusion_reg"),
    ("multi-modal − LiDAR-only, depth-corrected", "lidar_reg_seg_depth", "fusion_reg_seg_depth"),
    ("seg − no seg, LiDAR-only", "lidar_reg", "lidar_reg_seg"),
    ("seg − no seg, multi-modal", "fusion_reg", "fusion_reg_seg"),
)


def paper_difference(a: str, b: str) -> str:
    if a not in PAPER_T3 or b not in PAPER_T3:
        return "-"
    d = [y - x for x, y in zip(PAPER_T3[a], PAPER_T3[b], strict=True)]
    wrist = "-"
    if (a, b) == ("lidar_reg_seg", "fusion_reg_seg"):
        wrist = signed(PAPER_T2["wrist"][2] - PAPER_T2["wrist"][1])
    return f"{signed(d[0])} / {signed(d[1], ' cm')} / {signed(d[2])} / {wrist}"


def signed(v: float, unit: str = "") -> str:
    return f"{v:+.2f}{unit}"


def street_differences(groups: dict) -> str:
    """Every comparison the paper draws, per (rotation, seed) group that holds both of its rows."""
    header = ["comparison", "rotation", "seed", "ΔOKS@3D", "ΔMPJPE", "ΔOKS@2D", "Δwrist OKS@3D", "paper"]
    body = []
    for what, a, b in STREET_DIFFS:
        for (rot, seed), rows in groups.items():
            if a not in rows or b not in rows:
                continue
            ra, rb = rows[a]["metrics"], rows[b]["metrics"]
            wa, wb = part_oks(ra, "wrist"), part_oks(rb, "wrist")
            body.append(
                [what, f"±{rot:g}°", str(seed)]
                + [signed(100 * (rb["oks_acc_3d"] - ra["oks_acc_3d"]))]
                + [signed(100 * (rb["mpjpe_3d_m"] - ra["mpjpe_3d_m"]), " cm")]
                + [signed(100 * (rb["oks_acc_2d"] - ra["oks_acc_2d"]))]
                + ["-" if wa is None or wb is None else signed(100 * (wb - wa)), paper_difference(a, b)]
            )
    return md_table(header, body)


def street_section(runs: list[dict]) -> list[str]:
    """Rows trained and evaluated on `posefuse simulate --profile street` data (loose clothing,
    things in hand, mixed-pixel returns), grouped by rotation and seed: one Table 3 per group, the
    per-keypoint table of the first group with the run's own camera row, and the differences the
    paper's conclusions rest on."""
    groups = point_rows_by(runs, lambda c: (c["rotate_deg"], c.get("seed", 0)))
    groups = {g: groups[g] for g in sorted(groups, key=lambda g: (-g[0], g[1]))}
    s0 = runs[0]
    lq = {k: v for r in runs for k, v in r["label_quality"].items()}
    lines = [
        "## The street profile",
        "",
        f"Train `{s0['train']['path']}` ({s0['train']['count']}), held-out `{s0['test']['path']}` "
        f"({s0['test']['count']}), both `posefuse simulate --profile street` (docs/DATA.md), with "
        "the camera net trained on them. Pseudo labels: "
        + ", ".join(f"{k} {cm(v['mean_error_m'])}" for k, v in lq.items())
        + " from the 3D truth.",
        "",
        "Differences (b − a; OKS in points):",
        "",
        street_differences(groups),
    ]
    first = next(
        (item for item in groups.items() if {"lidar_reg_seg", "fusion_reg_seg"} <= item[1].keys()), None
    )
    if first is not None:
        (rot, seed), rows = first
        lines += [
            "",
            f"Per keypoint, rotation ±{rot:g}°, point-net seed {seed}:",
            "",
            table2({"camera": s0["rows"]["camera"], **rows}),
        ]
    for (rot, seed), rows in groups.items():
        lines += ["", f"Rotation ±{rot:g}° about z, point-net seed {seed}:", "", table3(paper_order(rows))]
    return [*lines, *commands(runs)]


def heading_error_table(table: list[dict]) -> str:
    names = [k for k in table[0] if k != "error_deg"]
    header = ["heading error", *[f"`{n}` OKS@3D / MPJPE / L-R swaps" for n in names]]
    body = [
        [f"{c['error_deg']:g}°"]
        + [
            f"{pct(c[n]['oks_acc_3d'])} / {cm(c[n]['mpjpe_3d_m'])} / {pct(c[n]['left_right_swap_rate'])}"
            for n in names
        ]
        for c in table
    ]
    return md_table(header, body)


def bundle_source(main: dict, others: list[dict]) -> dict | None:
    """The latest run that wrote a bundle: one given after the main ablation replaced its bundle."""
    return next((r for r in reversed([main, *others]) if "bundle" in r), None)


def default_bundle_section(run: dict, main: bool = True) -> list[str]:
    """The bundle written by the latest run given that wrote one (`--bundle`)."""
    b = run["bundle"]
    origin = (
        "this ablation"
        if main
        else f"`{run['command']}`, trained on `{run['train']['path']}`, evaluated on `{run['test']['path']}`"
    )
    return [
        "## Default bundle",
        "",
        f"`{b['path']}` ({b['size_mb']:.1f} MB), written by {origin}: fusion model from row "
        f"`{b['fusion_row']}`, LiDAR-only model from row `{b['lidar_row']}`; their held-out metrics are in "
        "its `manifest.json`.",
    ]


def results_markdown(
    s: dict,
    backbones: dict | None = None,
    by_range: list | None = None,
    notes: str | None = None,
    paper_recipe: list[dict] | None = None,
    heading_error: list[dict] | None = None,
    street: list[dict] | None = None,
    choices: str | None = None,
    preface: str | None = None,
) -> str:
    rows, pre, lq = s["rows"], s["preprocessing"], s["label_quality"]
    cam = rows["camera"]
    pc = next((r["config"] for k, r in rows.items() if k != "camera"), None)
    setup = [
        f"- train: `{s['train']['path']}`, {s['train']['count']} pedestrians; held-out test: "
        f"`{s['test']['path']}`, {s['test']['count']} pedestrians (another seed).",
        f"- pre-processing: S = {pre['image_size']}, heatmaps {pre['heatmap_size']}², "
        f"N = {pre['num_points']}, "
        f"smoothing {pre['smoothing_kernel']}×{pre['smoothing_kernel']} σ = {pre['smoothing_sigma']}, "
        f"T = {pre['lift_temperature']}, T_r = {s['t_r']}.",
        f"- camera net: {cam['config']['backbone']}, deconv width {cam['config']['deconv_channels']}, "
        f"{cam['params'] / 1e6:.2f} M parameters, {cam.get('epochs', 0):.1f} epochs "
        f"in {cam['train_s']:.0f} s, "
        f"Adam lr {cam['config']['lr']} (×0.1 at {cam['config']['decay_at']} of the run); ONNX Runtime CPU "
        f"latency at batch 1: {cam['ort_latency_ms_b1']:.2f} ms.",
    ]
    if pc:
        setup.append(
            f"- point nets: batch {pc['batch_size']}, {pc['optimizer'].upper()} lr {pc['lr']} "
            "with cosine decay, "
            f"λ = {pc['seg_weight']}, r = {pc['seg_radius']}·S, w_pos/w_neg = {pc['w_pos']}/{pc['w_neg']}, "
            f"random rotation ±{pc['rotate_deg']}° about z, {s.get('point_epochs', 0):.1f} epochs per row."
        )
    setup += [
        "- Evaluation on the exact points the server uses (`serve_xyz`/`serve_uv`) against the "
        "simulator's 3D "
        "truth; OKS@2D projects the 3D prediction into the full image and scores it against the exact 2D "
        "projections of the 3D truth.",
        "- Timings: " + ", ".join(f"{k[:-2]} {v:.0f} s" for k, v in s["timings"].items()) + ".",
    ]
    lines = [
        "# Results: the paper's ablation on simulated pedestrians",
        "",
        *([preface.strip(), ""] if preface else []),
        f"One command, {s['wall_s'] / 60:.1f} min wall time on {s['machine']}:",
        "",
        "```",
        s["command"],
        "```",
        "",
        *setup,
        "",
        "## Table 1: camera-only, LiDAR-only, multi-modal",
        "",
        table1(rows),
        "",
        "The paper's 3D numbers are on 986 Waymo pedestrians and its 2D numbers on its internal "
        "test set; ours "
        "are on the simulated held-out set, so the ordering and the gaps are what compares.",
        "",
        "## Table 2: per-keypoint OKS (left and right averaged)",
        "",
        table2(rows),
        "",
        "## Table 3: architecture ablation, plus depth-corrected pseudo labels",
        "",
        table3(rows),
        "",
        "## Pseudo-label quality",
        "",
        "Diagnostic only: the training labels compared with the 3D truth, which training never sees.",
        "",
        md_table(
            ["labels", "mean error", "labelled keypoints"],
            [[k, cm(v["mean_error_m"]), str(v["labels"])] for k, v in lq.items()],
        ),
    ]
    if paper_recipe:
        lines += ["", *paper_recipe_section(paper_recipe)]
    if street:
        lines += ["", *street_section(street)]
    if heading_error:
        lines += [
            "",
            "## Wrong box headings",
            "",
            "`python -m experiments.heading_error --test TEST --models RUN:ROW,...`: every held-out "
            "box's heading turned by the given error before pre-processing. L-R swaps: the share of "
            "persons predicted closer to the truth with left and right exchanged (the facing read "
            "backwards).",
            "",
            heading_error_table(heading_error),
        ]
    if by_range:
        lines += [
            "",
            "## By range: OKS@3D / MPJPE per LiDAR range band",
            "",
            "`python -m experiments.by_range --run RUN --test TEST --rows ...` on this run's checkpoints.",
            "",
            by_range_table(by_range),
        ]
    if notes:
        lines += ["", notes.strip()]
    if backbones:
        lines += [
            "",
            f"## Camera backbones: accuracy vs CPU latency (S = {backbones['image_size']})",
            "",
            (
                f"Each trained for the same {backbones['minutes']:g} min budget "
                if backbones.get("minutes")
                else "Each trained for the epochs in the table "
            )
            + f"(`{backbones.get('command', 'python -m experiments.backbones')}`).",
            "",
            backbone_table(backbones),
        ]
    bundle_run = bundle_source(s, street or [])
    if bundle_run is not None:
        lines += ["", *default_bundle_section(bundle_run, main=bundle_run is s)]
    if choices:
        lines += ["", choices.strip()]
    return "\n".join(lines) + "\n"


def main(argv=None):
    """Renders RESULTS.md from finished runs (to standard output unless --out is given)."""
    import argparse
    import json
    from pathlib import Path

    p = argparse.ArgumentParser(prog="python -m experiments.report", description=main.__doc__)
    p.add_argument("results", help="results.json written by experiments.ablation")
    p.add_argument("--backbones", help="backbones.json written by experiments.backbones")
    p.add_argument("--by-range", help="JSON written by experiments.by_range --json")
    p.add_argument("--notes", help="hand-written markdown (the analysis) placed after the tables")
    p.add_argument(
        "--paper-recipe", nargs="*", default=[], help="results.json of runs with the paper's [0, 2π) rotation"
    )
    p.add_argument("--heading-error", help="JSON written by experiments.heading_error --json")
    p.add_argument("--street", nargs="*", default=[], help="results.json of runs on --profile street data")
    p.add_argument("--choices", help="markdown placed last (docs/results-choices.md: choices and deviations)")
    p.add_argument("--preface", help="markdown placed first (docs/results-convention.md: what counts)")
    p.add_argument(
        "--out", help="write the markdown to this file (e.g. docs/RESULTS.md) instead of printing it"
    )
    a = p.parse_args(argv)
    summary = json.loads(Path(a.results).read_text())
    load = lambda path: json.loads(Path(path).read_text()) if path else None  # noqa: E731
    text = lambda path: Path(path).read_text() if path else None  # noqa: E731
    md = results_markdown(
        summary,
        load(a.backbones),
        load(a.by_range),
        text(a.notes),
        [load(r) for r in a.paper_recipe],
        load(a.heading_error),
        [load(r) for r in a.street],
        text(a.choices),
        text(a.preface),
    )
    if a.out:
        Path(a.out).write_text(md)
        print(f"wrote {a.out}")
    else:
        print(md, end="")


if __name__ == "__main__":
    main()
