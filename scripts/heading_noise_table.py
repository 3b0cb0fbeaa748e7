"""Bundles under box-heading noise, through the serving path: runs `posefuse eval --heading-noise`
for every bundle × mode × noise and prints the measurements behind docs/RESULTS.md's "A model that
needs no heading": OKS@3D, MPJPE (every labelled keypoint, occluded or not, as Waymo counts; the
visible-only breakdown beside them), the left/right swap rate (overall and for persons showing the
sensor their back) and the median facing error. Standard library only.

  python scripts/heading_noise_table.py --bin target/release/posefuse --data DIR \\
      --bundles models/default,models/view,models/default@models/view --noise 0,15,45,90,180,uniform

A bundle written MAIN@STAGE serves MAIN with STAGE as its heading stage (`--heading-model`);
a suffix :refine=N adds N passes of heading refinement (`--heading-refine N`), e.g.
models/default@models/view:refine=3.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys


def parse_bundle(bundle: str) -> tuple[str, str, int]:
    """MAIN[@STAGE][:refine=N] -> (main, stage or "", refinement passes)."""
    spec, _, refine = bundle.partition(":refine=")
    main, _, stage = spec.partition("@")
    return main, stage, int(refine or 0)


def run_eval(binary: str, data: str, bundle: str, mode: str, noise: str, seed: int) -> dict:
    main, stage, refine = parse_bundle(bundle)
    cmd = [binary, "eval", "--data", data, "--model-dir", main, "--mode", mode, "--json"]
    if stage:
        cmd += ["--heading-model", stage]
    if refine:
        cmd += ["--heading-refine", str(refine)]
    cmd += ["--noise-seed", str(seed)]
    if noise not in ("", "0"):
        cmd += ["--heading-noise", noise]
    out = subprocess.run(cmd, check=True, capture_output=True, text=True, env=os.environ)
    return json.loads(out.stdout)


def row(report: dict, mode: str) -> dict:
    """One mode's numbers; the mode is forced, so the visible-only breakdown of `all` is its own."""
    m, d = report["metrics"][mode], report["diagnostics"][mode]
    visible = report.get("breakdown", {}).get("visible", {})
    back = d.get("swaps_by_view", {}).get("back")
    return {
        "persons": m["count_3d"],
        "oks_acc_3d": m["oks_acc_3d"],
        "mpjpe_3d_m": m["mpjpe_3d_m"],
        "oks_acc_3d_visible": visible.get("oks_acc_3d"),
        "mpjpe_3d_m_visible": visible.get("mpjpe_3d_m"),
        "swap_rate": d["left_right_swap_rate"],
        "swap_rate_back": back["swap_rate"] if back else None,
        "facing_error_median_deg": d["facing_error_median_deg"],
    }


def table(rows: list[dict]) -> str:
    pct = lambda v: "-" if v is None else f"{100 * v:.1f} %"  # noqa: E731
    lines = [
        "| bundle | mode | heading error | persons | OKS@3D | MPJPE | L-R swaps | swaps, back to sensor "
        "| facing error (median) | visible keypoints only: OKS@3D / MPJPE |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    cm = lambda v: "-" if v is None else f"{100 * v:.2f} cm"  # noqa: E731
    for r in rows:
        facing = "-" if r["facing_error_median_deg"] is None else f"{r['facing_error_median_deg']:.1f}°"
        noise = r["noise"] if r["noise"] == "uniform" else f"{r['noise']}°"
        lines.append(
            f"| {r['version']} | {r['mode']} | {noise} | {r['persons']} | {pct(r['oks_acc_3d'])} "
            f"| {cm(r['mpjpe_3d_m'])} | {pct(r['swap_rate'])} | {pct(r['swap_rate_back'])} | {facing} "
            f"| {pct(r.get('oks_acc_3d_visible'))} / {cm(r.get('mpjpe_3d_m_visible'))} |"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--bin", default="target/release/posefuse")
    p.add_argument("--data", required=True, help="simulator output with request fixtures")
    p.add_argument("--bundles", required=True, help="comma-separated bundle directories")
    p.add_argument("--modes", default="fusion,lidar")
    p.add_argument("--noise", default="0,15,45,90,180,uniform")
    p.add_argument("--noise-seed", type=int, default=0)
    p.add_argument("--json", help="also write the rows here")
    a = p.parse_args(argv)
    rows = []
    for bundle in a.bundles.split(","):
        for mode in a.modes.split(","):
            for noise in a.noise.split(","):
                report = run_eval(a.bin, a.data, bundle, mode, noise, a.noise_seed)
                version = f"{report['model']['name']} {report['model']['version']}"
                _, stage, refine = parse_bundle(bundle)
                if stage:
                    version += " + heading stage " + stage
                if refine:
                    version += f" + {refine} refinement passes"
                rows.append({"bundle": bundle, "version": version, "mode": mode, "noise": noise, **row(report, mode)})
                print(f"{bundle} {mode} {noise}: {rows[-1]}", file=sys.stderr)
    print(table(rows))
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
