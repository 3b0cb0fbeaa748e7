"""The paper's ablation through the serving path: each pair of an ablation run's point nets
(LiDAR-only and fusion, per architecture row) exported as a bundle beside the run's camera net,
scored by `posefuse eval` on request fixtures, and Tables 1-3 over several point-net seeds.

    python -m experiments.served eval --run ../runs/abl_s0 --camera ../runs/abl_s0/camera.pt \\
        --data ../data/hard_req_s3 --posefuse ../target/release/posefuse
    python -m experiments.served tables --data-name hard_req_s3 ../runs/abl_s0 ../runs/abl_s2

`eval` writes `<run>/served/<data name>/<mode>_<pair>.json` (and `camera.json`), each the
unchanged output of `posefuse eval --json`; `tables` reads them back. Exact box headings unless
`--heading-noise` is given (then the files carry its name as a suffix)."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from experiments.report import PAPER_T1, PAPER_T2, PAPER_T3, md_table, part_oks
from posefuse_train.keypoints import PARTS

# Architecture rows as checkpoint suffixes: `fusion_<pair>.pt` and `lidar_<pair>.pt`.
PAIRS = ("reg", "reg_seg", "reg_seg_depth")
PAIR_LABELS = {
    "reg": ("✓", "", "eq. 1"),
    "reg_seg": ("✓", "✓", "eq. 1"),
    "reg_seg_depth": ("✓", "✓", "eq. 1 + depth correction"),
}


def served_dir(run: Path, data_name: str) -> Path:
    return run / "served" / data_name


def result_name(mode: str, pair: str | None, noise: str | None) -> str:
    stem = "camera" if mode == "camera" else f"{mode}_{pair}"
    return f"{stem}_{noise}.json" if noise else f"{stem}.json"


def present_pairs(run: Path) -> list[str]:
    return [p for p in PAIRS if (run / f"fusion_{p}.pt").exists() and (run / f"lidar_{p}.pt").exists()]


def export_bundle(camera: Path, fusion: Path, lidar: Path, out: Path) -> None:
    from posefuse_train.export import main as export_main

    export_main(["--camera", str(camera), "--fusion", str(fusion), "--lidar", str(lidar), "--out", str(out)])


def posefuse_eval(posefuse: Path, data: Path, bundle: Path, mode: str, noise: str | None, seed: int) -> dict:
    cmd = [str(posefuse), "eval", "--data", str(data), "--model-dir", str(bundle), "--mode", mode, "--json"]
    if noise:
        cmd += ["--heading-noise", noise, "--noise-seed", str(seed)]
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({p.returncode}): {p.stderr[-2000:]}")
    return json.loads(p.stdout)


def eval_run(
    run: Path,
    camera: Path,
    data: Path,
    posefuse: Path,
    noise: str | None = None,
    noise_seed: int = 0,
    export=export_bundle,
    evaluate=posefuse_eval,
) -> list[Path]:
    """Bundles of each point-net pair of `run` (exported once, kept as `<run>/bundle_<pair>`) scored
    in fusion and LiDAR-only mode, and the camera net alone once; returns the files written."""
    pairs = present_pairs(run)
    if not pairs:
        raise SystemExit(f"{run}: no pair of fusion_<row>.pt and lidar_<row>.pt for rows {', '.join(PAIRS)}")
    out = served_dir(run, data.name)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for i, pair in enumerate(pairs):
        bundle = run / f"bundle_{pair}"
        if not (bundle / "manifest.json").exists():
            export(camera, run / f"fusion_{pair}.pt", run / f"lidar_{pair}.pt", bundle)
        for mode in ("fusion", "lidar") + (("camera",) if i == 0 else ()):
            path = out / result_name(mode, pair, noise)
            path.write_text(json.dumps(evaluate(posefuse, data, bundle, mode, noise, noise_seed), indent=1))
            written.append(path)
    return written


def load_rows(run: Path, data_name: str, noise: str | None = None) -> dict:
    """{row: metrics} of one run's served results; rows as the ablation names them
    (`lidar_reg_seg`, `fusion_reg`, ..., `camera`)."""
    d = served_dir(run, data_name)
    rows = {}
    for mode in ("fusion", "lidar", "camera"):
        for pair in (None,) if mode == "camera" else PAIRS:
            path = d / result_name(mode, pair, noise)
            if path.exists():
                rows["camera" if mode == "camera" else f"{mode}_{pair}"] = json.loads(path.read_text())[
                    "metrics"
                ][mode]
    return rows


def over_seeds(seeds: list[dict], row: str, value) -> list[float | None]:
    return [value(s[row]) if row in s else None for s in seeds]


def cell(values: list[float | None], scale: float, unit: str, signed: bool = False) -> str:
    """`mean (a / b)`: the mean over seeds, then each seed's value; `signed` for differences."""
    known = [v for v in values if v is not None]
    if not known:
        return "-"
    fmt = "{:+.2f}" if signed else "{:.2f}"
    mean = fmt.format(scale * sum(known) / len(known))
    each = " / ".join("-" if v is None else fmt.format(scale * v) for v in values)
    return f"{mean}{unit} ({each})" if len(values) > 1 else f"{mean}{unit}"


def pct_cell(values):
    return cell(values, 100, " %")


def cm_cell(values):
    return cell(values, 100, " cm")


def headline_cells(seeds: list[dict], row: str) -> list[str]:
    """OKS@3D, MPJPE and OKS@2D of one row over the seeds."""
    return [
        pct_cell(over_seeds(seeds, row, lambda m: m["oks_acc_3d"])),
        cm_cell(over_seeds(seeds, row, lambda m: m["mpjpe_3d_m"])),
        pct_cell(over_seeds(seeds, row, lambda m: m["oks_acc_2d"])),
    ]


def ratio_to_hips(metrics: dict, part: str) -> float | None:
    """A part's OKS@3D over the hips', the shape of the paper's LiDAR-only profile."""
    num, hip = part_oks(metrics, part), part_oks(metrics, "hip")
    return num / hip if num is not None and hip else None


def diff_cell(a: list, b: list, scale: float, unit: str) -> str:
    return cell(
        [x - y if x is not None and y is not None else None for x, y in zip(a, b, strict=True)],
        scale,
        unit,
        True,
    )


def table1(seeds: list[dict], pair: str) -> str:
    header = ["method", "OKS@3D", "MPJPE", "OKS@2D", "paper OKS@3D", "paper MPJPE", "paper OKS@2D"]
    body = []
    for label, row in (
        ("camera-only", "camera"),
        ("LiDAR-only", f"lidar_{pair}"),
        ("multi-modal", f"fusion_{pair}"),
    ):
        p = PAPER_T1[label]
        body.append([label, *headline_cells(seeds, row), f"{p[0]:.2f} %", f"{p[1]:.2f} cm", f"{p[2]:.2f} %"])
    return md_table(header, body)


def table2(seeds: list[dict], pair: str) -> str:
    rows = (("camera-only", "camera"), ("LiDAR-only", f"lidar_{pair}"), ("multi-modal", f"fusion_{pair}"))
    header = ["part"]
    for label, _ in rows:
        header += [f"{label} OKS@3D", "paper"]
    header += ["multi-modal − LiDAR-only", "paper"]
    body = []
    for part in PARTS:
        cells, per_row = [part], {}
        for i, (_, row) in enumerate(rows):
            per_row[row] = over_seeds(seeds, row, lambda m, part=part: part_oks(m, part))
            cells += [pct_cell(per_row[row]), f"{PAPER_T2[part][i]:.2f} %"]
        cells += [diff_cell(per_row[rows[2][1]], per_row[rows[1][1]], 100, " pt")]
        cells += [f"{PAPER_T2[part][2] - PAPER_T2[part][1]:+.2f} pt"]
        body.append(cells)
    return md_table(header, body)


def table3(seeds: list[dict]) -> str:
    header = ["Reg.", "Seg.", "Camera", "labels", "OKS@3D", "MPJPE", "OKS@2D", "PCK@10cm"]
    header += ["paper OKS@3D", "paper MPJPE", "paper OKS@2D"]
    body = []
    for modality in ("lidar", "fusion"):
        for pair in PAIRS:
            row = f"{modality}_{pair}"
            if not any(row in s for s in seeds):
                continue
            reg, seg, labels = PAIR_LABELS[pair]
            p = PAPER_T3.get(row)
            body.append(
                [reg, seg, "✓" if modality == "fusion" else "", labels]
                + headline_cells(seeds, row)
                + [pct_cell(over_seeds(seeds, row, lambda m: m["pck_3d_10cm"]))]
                + ([f"{p[0]:.2f} %", f"{p[1]:.2f} cm", f"{p[2]:.2f} %"] if p else ["-", "-", "-"])
            )
    return md_table(header, body)


def margins(seeds: list[dict]) -> str:
    """Fusion minus LiDAR-only per architecture row: OKS@3D, MPJPE and wrist OKS@3D."""
    header = ["row", "OKS@3D", "MPJPE", "wrist OKS@3D", "LiDAR-only wrist / hip", "LiDAR-only elbow / hip"]
    body = []
    for pair in PAIRS:
        f, lid = f"fusion_{pair}", f"lidar_{pair}"
        if not any(f in s and lid in s for s in seeds):
            continue
        body.append(
            [pair]
            + [diff_cell(*(over_seeds(seeds, r, lambda m: m["oks_acc_3d"]) for r in (f, lid)), 100, " pt")]
            + [diff_cell(*(over_seeds(seeds, r, lambda m: m["mpjpe_3d_m"]) for r in (f, lid)), 100, " cm")]
            + [
                diff_cell(
                    *(over_seeds(seeds, r, lambda m: part_oks(m, "wrist")) for r in (f, lid)), 100, " pt"
                )
            ]
            + [cell(over_seeds(seeds, lid, lambda m: ratio_to_hips(m, "wrist")), 1, "")]
            + [cell(over_seeds(seeds, lid, lambda m: ratio_to_hips(m, "elbow")), 1, "")]
        )
    return md_table(header, body)


def render(seeds: list[dict], pair: str) -> str:
    return "\n\n".join(
        [
            f"Table 1 (point nets: `{pair}`)",
            table1(seeds, pair),
            f"Table 2, per keypoint, left and right averaged (point nets: `{pair}`)",
            table2(seeds, pair),
            "Table 3",
            table3(seeds),
            "Fusion − LiDAR-only",
            margins(seeds),
        ]
    )


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m experiments.served", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    e = sub.add_parser("eval", help="export each point-net pair of a run and score it with `posefuse eval`")
    e.add_argument("--run", type=Path, required=True, help="ablation run directory (<mode>_<row>.pt)")
    e.add_argument("--camera", type=Path, required=True, help="the camera checkpoint the run's rows used")
    e.add_argument("--data", type=Path, required=True, help="request fixtures (`posefuse simulate` output)")
    e.add_argument("--posefuse", type=Path, default=Path("../target/release/posefuse"))
    e.add_argument("--heading-noise", help="as `posefuse eval --heading-noise` (e.g. uniform)")
    e.add_argument("--noise-seed", type=int, default=0)
    t = sub.add_parser("tables", help="Tables 1-3 over the runs' served results (one run per point-net seed)")
    t.add_argument("runs", type=Path, nargs="+")
    t.add_argument("--data-name", required=True, help="the request set's folder name")
    t.add_argument("--pair", default="reg_seg", choices=PAIRS, help="the point nets of Tables 1 and 2")
    t.add_argument("--heading-noise")
    t.add_argument("--out", type=Path, help="write the markdown here (default: standard output)")
    a = p.parse_args(argv)
    if a.command == "eval":
        for path in eval_run(a.run, a.camera, a.data, a.posefuse, a.heading_noise, a.noise_seed):
            print(path)
        return
    seeds = [load_rows(r, a.data_name, a.heading_noise) for r in a.runs]
    missing = [str(r) for r, s in zip(a.runs, seeds, strict=True) if not s]
    if missing:
        raise SystemExit(f"no served results for {a.data_name} in: {', '.join(missing)} (run `eval` first)")
    md = render(seeds, a.pair)
    if a.out:
        a.out.write_text(md + "\n")
    else:
        sys.stdout.write(md + "\n")


if __name__ == "__main__":
    main()
