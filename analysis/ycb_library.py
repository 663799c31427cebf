"""An object library of scanned objects: the six YCB objects Drake's model repository carries.

    python analysis/ycb_library.py MESHES_DIR --out LIBRARY_DIR

MESHES_DIR holds the `<id>_textured.gltf` files (with their `.bin` buffers) of
https://github.com/RobotLocomotion/models, folder `ycb/meshes/` (the YCB Object and Model
Set's scans, CC BY 4.0: see `ycb/meshes/LICENSE.txt` there); textures are not needed.
Each is imported with `drake-grasp objects import`'s function (glTF is y-up, turned to
z-up) as the test-split object `ycb_<id>`, with a density that gives the YCB set's
published mass over its mesh's convex hull (the volume the import uses for a scan that is
not watertight). Then `drake-grasp evaluate ... --objects LIBRARY_DIR` runs on them, e.g.
the clutter-removal experiments (`analysis/results/clutter-removal/PLAN.md`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

# The YCB Object and Model Set's published masses [kg] (Calli et al., 2015).
YCB_MASS_KG = {"003_cracker_box": 0.411, "004_sugar_box": 0.514,
               "005_tomato_soup_can": 0.349, "006_mustard_bottle": 0.603,
               "009_gelatin_box": 0.097, "010_potted_meat_can": 0.370}


def density_for(mesh_file: Path, mass_kg: float) -> float:
    """The density [kg/m^3] that gives `mass_kg` over the file's convex hull."""
    import trimesh

    scene = trimesh.load_scene(str(mesh_file), process=False)
    volume = float(scene.to_geometry().convex_hull.volume)
    if not volume > 0:
        raise ValueError(f"{mesh_file}: its convex hull has no volume")
    return mass_kg / volume


def make_library(meshes: Path, out: Path, *, overwrite: bool = False) -> list[dict]:
    """Imports every object of `YCB_MASS_KG` from `meshes` into `out`; returns one row
    per object (id, mass asked and given, extents)."""
    from tqdm import tqdm

    from drake_grasp.objects import import_mesh

    missing = [k for k in YCB_MASS_KG if not (meshes / f"{k}_textured.gltf").is_file()]
    if missing:
        raise FileNotFoundError(f"{meshes}: no {missing[0]}_textured.gltf (expected the "
                                "ycb/meshes folder of RobotLocomotion/models)")
    rows = []
    for key, mass in tqdm(YCB_MASS_KG.items(), desc="import", unit="object"):
        mesh_file = meshes / f"{key}_textured.gltf"
        info = import_mesh(mesh_file, name=f"ycb_{key}", library_dir=out,
                           density_kg_m3=density_for(mesh_file, mass), overwrite=overwrite)
        rows.append({"id": info.id, "ycb_mass_kg": mass, "mass_kg": round(info.mass_kg, 4),
                     "extents_m": [round(float(x), 4) for x in info.extents_m]})
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("meshes", type=Path, help="RobotLocomotion/models' ycb/meshes folder")
    parser.add_argument("--out", type=Path, required=True, help="library folder to write")
    parser.add_argument("--overwrite", action="store_true", help="replace objects already there")
    args = parser.parse_args(argv)
    try:
        rows = make_library(args.meshes, args.out, overwrite=args.overwrite)
    except (FileNotFoundError, FileExistsError, ValueError) as e:
        print(f"ycb_library: error: {e}", file=sys.stderr)
        return 2
    for row in rows:
        print(row)
    return 0


if __name__ == "__main__":
    sys.exit(main())
