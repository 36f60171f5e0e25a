"""How much a footprint's yaw relative to the gel changes the virtual rig's contact: force and depth.

For each non-axisymmetric default indenter, builds (or finds cached) the contact
tables of the default rig with the footprint unturned and turned by its yaw
relative to the true gel (``[sim.rig_pose] gel_yaw_deg``, or ``--yaw``), and
compares, over the tabulated depths: the normal force, the shear force at half
the gross-slip shift along gel x and y, and the surface depth field: its rms
difference over the contact box (um), its largest difference (um: at cells the
turned edge crosses) and the fraction of contact cells that enter or leave the
contact. Prints a table; ``--json`` for the numbers.

    PYTHONPATH=. python tools/footprint_yaw.py [--yaw -0.6] [--json]
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from labrig.config import load_rig
from labrig.indenters import load_indenters
from labrig.sim.truth_config import sim_config, true_contact_table

#: Below this normal force a relative difference is noise of the first touching cells, N.
FORCE_FLOOR_N = 0.5


def compare(name: str, yaw_deg: float | None) -> dict[str, float]:
    rig = load_rig()
    indenter = load_indenters()[name]
    true_yaw_deg = sim_config(rig).rig_pose.gel_yaw_deg
    turn = indenter.footprint_yaw_deg(true_yaw_deg) if yaw_deg is None else indenter.reduced_turn_deg(yaw_deg)
    out: dict[str, float] = {"yaw_deg": turn}
    normal_rel, shear_rel, depth_max_um, depth_rms_um, flipped = 0.0, 0.0, 0.0, 0.0, 0.0
    for direction in (0.0, 90.0):
        flat = true_contact_table(indenter, rig, direction_deg=direction, yaw_deg=0.0)
        turned = true_contact_table(indenter, rig, direction_deg=direction, yaw_deg=turn)
        loaded = flat.normal_force_n > FORCE_FLOOR_N
        ratio = turned.normal_force_n[loaded] / flat.normal_force_n[loaded]
        normal_rel = max(normal_rel, float(np.max(np.abs(ratio - 1))))
        for depth in flat.depths_mm[loaded]:
            shift = 0.5 * float(np.interp(depth, flat.shear_depths_mm, flat.slip_shift_mm)) * flat.direction
            a = flat.fields(depth, shift)
            b = turned.fields(depth, shift)
            along = flat.direction
            shear_rel = max(shear_rel, abs(float(b.force_n[:2] @ along) / float(a.force_n[:2] @ along) - 1))
            box = flat.box.slices
            diff = (b.depth_mm - a.depth_mm)[box].astype(np.float64)
            depth_max_um = max(depth_max_um, float(np.max(np.abs(diff))) * 1e3)
            depth_rms_um = max(depth_rms_um, float(np.sqrt(np.mean(diff**2))) * 1e3)
            flipped = max(flipped, float(np.sum(a.contact_mask != b.contact_mask)) / max(int(a.contact_mask.sum()), 1))
    out.update(normal_force_rel_max=normal_rel, shear_force_rel_max=shear_rel, depth_rms_um_max=depth_rms_um,
               depth_abs_max_um=depth_max_um, contact_cells_changed_max=flipped)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--yaw", type=float, default=None, help="footprint yaw relative to the gel, deg (default: the rig's)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    rows = {name: compare(name, args.yaw) for name in ("square", "ridge")}
    if args.json:
        print(json.dumps(rows, indent=2))
        return
    print(f"{'indenter':10} {'yaw deg':>8} {'normal F':>9} {'shear F':>9} {'depth rms um':>13} {'depth max um':>13} "
          f"{'contact cells':>14}")
    for name, r in rows.items():
        print(f"{name:10} {r['yaw_deg']:8.2f} {r['normal_force_rel_max']:9.2%} {r['shear_force_rel_max']:9.2%} "
              f"{r['depth_rms_um_max']:13.1f} {r['depth_abs_max_um']:13.1f} {r['contact_cells_changed_max']:14.1%}")


if __name__ == "__main__":
    main()
