"""Computes APE and RPE with evo's Python API and prints the statistics as JSON.

Usage: evo_metrics.py {kitti|tum} REF EST ALIGN DELTA DELTA_UNIT

ALIGN: se3 | sim3 | none (APE only). DELTA_UNIT: f (frames) or m (metres). TUM trajectories
are associated by time with evo's default max difference (0.01 s). Output:
{"ape": {...translation stats...}, "ape_rot_deg": {...}, "rpe": {...}, "rpe_rot_deg": {...},
 "matched": N, "rpe_pairs": M}
"""
import copy
import json
import sys

from evo.core import metrics, sync
from evo.tools import file_interface


def stats(metric):
    return {k: float(v) for k, v in metric.get_all_statistics().items()}


def main():
    fmt, ref_path, est_path, align, delta, unit = sys.argv[1:7]
    if fmt == "kitti":
        ref = file_interface.read_kitti_poses_file(ref_path)
        est = file_interface.read_kitti_poses_file(est_path)
    else:
        ref = file_interface.read_tum_trajectory_file(ref_path)
        est = file_interface.read_tum_trajectory_file(est_path)
        ref, est = sync.associate_trajectories(ref, est)
    out = {"matched": est.num_poses}

    aligned = copy.deepcopy(est)
    if align in ("se3", "sim3"):
        aligned.align(ref, correct_scale=(align == "sim3"))
    for key, relation in (("ape", metrics.PoseRelation.translation_part),
                          ("ape_rot_deg", metrics.PoseRelation.rotation_angle_deg)):
        m = metrics.APE(relation)
        m.process_data((ref, aligned))
        out[key] = stats(m)

    unit = metrics.Unit.frames if unit == "f" else metrics.Unit.meters
    for key, relation in (("rpe", metrics.PoseRelation.translation_part),
                          ("rpe_rot_deg", metrics.PoseRelation.rotation_angle_deg)):
        m = metrics.RPE(relation, float(delta), unit, all_pairs=False)
        m.process_data((ref, est))
        out[key] = stats(m)
        out["rpe_pairs"] = len(m.error)
    json.dump(out, sys.stdout)


if __name__ == "__main__":
    main()
