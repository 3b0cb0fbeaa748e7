"""scripts/peer_compare.py's agreement check: the two servers' answers matched by person id, only
persons both answered with the fusion network, every labelled keypoint in the MPJPE."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from peer_compare import accuracy, keypoints
from python_peer.sampling import sample

GT = np.zeros((13, 3))


def fixture(*ids: str, occluded: int | None = None) -> dict:
    visible = [True] * 13
    flags = [False] * 13
    if occluded is not None:
        visible[occluded], flags[occluded] = False, True
    truth = {"keypoints_3d": {"xyz": GT.tolist(), "visible": visible, "occluded": flags}}
    return {"persons": [{"id": i, "ground_truth": truth} for i in ids]}


def served(pid: str, offset: float, mode: str = "fusion", num_points: str = "100") -> dict:
    xyz = (GT + [offset, 0.0, 0.0]).tolist()
    return {"id": pid, "mode": mode, "num_points": num_points, "keypoints": [{"xyz": p} for p in xyz]}


def peer(pid: str, offset: float, mode: str = "fusion") -> dict:
    return {"id": pid, "mode": mode, "keypoints_3d": (GT + [offset, 0.0, 0.0]).tolist()}


def test_both_answer_formats_read_as_keypoints():
    assert np.allclose(keypoints(served("a", 0.5)), GT + [0.5, 0, 0])
    assert np.allclose(keypoints(peer("a", 0.25)), GT + [0.25, 0, 0])
    assert keypoints({"id": "a", "keypoints_3d": None}) is None
    assert keypoints({"id": "a", "keypoints": []}) is None


def test_persons_are_matched_by_id_not_by_position():
    # the server leaves out a person without points; its answers no longer line up by position
    fx = [fixture("p0", "p1", "p2")]
    ours = [{"persons": [served("p0", 0.10), served("p2", 0.30)]}]
    theirs = [{"persons": [peer("p0", 0.10), peer("p1", 0.20), peer("p2", 0.31)]}]
    r = accuracy(fx, ours, theirs)
    assert r["fusion_persons"] == {"all_points_taken": 2, "points_chosen": 0}
    assert r["apart_cm"]["all_points_taken"] == 0.5  # (0 + 1 cm) / 2
    assert r["mpjpe_cm"] == {"posefuse": 20.0, "peer": 20.5}


def test_only_fusion_answers_on_both_sides_count_and_chosen_points_are_split():
    fx = [fixture("p0", "p1", "p2")]
    answered = [served("p0", 0.1, mode="camera"), served("p1", 0.1, num_points="300"), served("p2", 0.1)]
    ours = [{"persons": answered}]
    theirs = [{"persons": [peer("p0", 0.1, mode="lidar"), peer("p1", 0.14), peer("p2", 0.1, mode="lidar")]}]
    r = accuracy(fx, ours, theirs)
    assert r["fusion_persons"] == {"all_points_taken": 0, "points_chosen": 1}
    assert r["apart_cm"] == {"all_points_taken": None, "points_chosen": 4.0}


def test_an_occluded_keypoint_counts_as_labelled():
    fx = [fixture("p0", occluded=3)]
    ours = [{"persons": [served("p0", 0.0)]}]
    moved = peer("p0", 0.0)
    moved["keypoints_3d"][3] = [1.3, 0.0, 0.0]  # only the occluded keypoint is off, by 1.3 m
    r = accuracy(fx, ours, [{"persons": [moved]}])
    assert r["mpjpe_cm"]["peer"] == 10.0  # 130 cm / 13 labelled keypoints


@pytest.mark.parametrize("sampling,key", [("nearest", "features"), ("bilinear", "bilinear_features")])
def test_the_peer_samples_heatmaps_as_the_golden_vectors_say(sampling, key):
    """The peer's heatmap sampling is the server's and the trainer's (tests/golden/fusion.json)."""
    g = json.loads((Path(__file__).resolve().parents[2] / "tests/golden/fusion.json").read_text())
    smooth = np.asarray(g["smoothed"], np.float32).reshape(g["k"], g["h"], g["w"])
    finite = np.array([u is not None for u in g["uv"]])
    uv = np.asarray([u if u is not None else [0.0, 0.0] for u in g["uv"]], np.float32)
    got = sample(smooth, uv, g["image_size"], sampling) * finite[:, None]
    want = np.asarray(g[key], np.float32).reshape(len(uv), g["k"])
    assert np.abs(got - want).max() <= 1e-6
