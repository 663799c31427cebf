"""The shapes of the 10 procedural categories: per category, a parameter sampler with
dimension ranges taken from typical real objects (cited per category) and a builder that
turns the parameters into a handful (<= 12) of convex parts.

`SHAPES` maps a category name to its (sample, build) pair; `objects.categories` pairs them
with each category's seed, count, density, colour and contact material, and states the
conventions every builder follows (metres, z up, canonical resting pose, touching parts,
horizontal extent <= 75 mm).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from drake_grasp.objects import geometry as g
from drake_grasp.objects.geometry import Part

if TYPE_CHECKING:  # annotations only
    import trimesh

MM = 1e-3
Params = dict[str, float]


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


# ----------------------------------------------------------------------------
# mug: ceramic, hollow. 8-12 oz mugs are 72-85 mm wide and 85-105 mm tall
# with 4-6 mm walls and weigh 0.25-0.4 kg. The width is capped at 75 mm so an
# 85 mm gripper can also close around the body, not only on the rim/handle.

MUG_WALL_SEGMENTS = 8


def _sample_mug(rng: np.random.Generator) -> Params:
    height = _u(rng, 78, 105) * MM
    bottom = _u(rng, 5, 9) * MM
    inner_h = height - bottom
    return {
        "outer_radius": _u(rng, 32, 37.5) * MM,
        "height": height,
        "wall": _u(rng, 3.5, 5.5) * MM,
        "bottom": bottom,
        "handle_width": _u(rng, 9, 14) * MM,
        "handle_bar": _u(rng, 6, 9) * MM,
        "handle_reach": _u(rng, 20, 32) * MM,
        "handle_z0": bottom + _u(rng, 0.08, 0.2) * inner_h,
        "handle_z1": height - _u(rng, 0.06, 0.18) * inner_h,
    }


def _build_mug(p: Params, density: float) -> list[Part]:
    r_out, h, tb = p["outer_radius"], p["height"], p["bottom"]
    half = np.pi / MUG_WALL_SEGMENTS
    # Inner chord corners chosen so the mean wall thickness equals p["wall"].
    r_in = (r_out - p["wall"]) / (0.5 * (1.0 + np.cos(half)))
    parts = [Part("bottom", g.cylinder_z(r_out, 0.0, tb), density)]
    for k in range(MUG_WALL_SEGMENTS):
        centre = 2 * half * k
        outer = np.linspace(centre - half, centre + half, 4)  # 3 facets per segment
        inner = np.array([centre - half, centre + half])
        xy = np.vstack(
            [
                np.column_stack([r_out * np.cos(outer), r_out * np.sin(outer)]),
                np.column_stack([r_in * np.cos(inner), r_in * np.sin(inner)]),
            ]
        )
        pts = np.vstack([np.column_stack([xy, np.full(len(xy), z)]) for z in (tb, h)])
        parts.append(Part(f"wall_{k}", g.hull(pts), density))
    # C-shaped handle on +x; the arms reach 0.5 mm into the flat middle facet of
    # wall segment 0 so the handle is attached, not merely touching.
    x0 = r_out * np.cos(half / 3) - 0.5 * MM
    x1 = r_out + p["handle_reach"]
    hw, bar = p["handle_width"], p["handle_bar"]
    z0, z1 = p["handle_z0"], p["handle_z1"]
    xm = (x0 + x1) / 2
    parts += [
        Part("handle_low", g.box((x1 - x0, hw, bar), (xm, 0, z0 + bar / 2)), density),
        Part("handle_high", g.box((x1 - x0, hw, bar), (xm, 0, z1 - bar / 2)), density),
        Part("handle_bar", g.box((bar, hw, z1 - z0 - 2 * bar), (x1 - bar / 2, 0, (z0 + z1) / 2)), density),
    ]
    return parts


# ----------------------------------------------------------------------------
# hammer: lying on its side, handle along x, head along y. Light claw/ball-pein
# hammers (8-16 oz heads, 0.23-0.45 kg steel) are 250-330 mm long with a
# 90-120 mm head and a handle of about 30 x 22 mm; total 0.35-0.6 kg.

STEEL_KG_M3 = 7850.0


def _sample_hammer(rng: np.random.Generator) -> Params:
    return {
        "handle_length": _u(rng, 220, 300) * MM,
        "grip_fraction": _u(rng, 0.35, 0.5),
        "handle_width": _u(rng, 24, 30) * MM,  # in the swing direction (y)
        "handle_thickness": _u(rng, 18, 23) * MM,  # sideways (z when lying)
        "grip_extra": _u(rng, 2, 5) * MM,
        "head_size": _u(rng, 17, 23) * MM,  # head cross-section
        "eye_margin": _u(rng, 3, 6) * MM,
        "face_length": _u(rng, 22, 36) * MM,
        "claw_length": _u(rng, 28, 42) * MM,
        "claw_curl": _u(rng, 4, 14) * MM,
    }


def _build_hammer(p: Params, density: float) -> list[Part]:
    d = p["head_size"]
    w, t = p["handle_width"], p["handle_thickness"]
    gw, gt = w + p["grip_extra"], t + p["grip_extra"]
    by = w + p["eye_margin"]  # eye block is wider than the handle it holds
    zc = 0.5 * max(d, gt)  # common mid-plane: the hammer rests on head and grip
    grip_len = p["grip_fraction"] * p["handle_length"]
    shaft_len = p["handle_length"] - grip_len
    x_shaft = -d / 2
    parts = [
        Part("eye_block", g.box((d, by, d), (0, 0, zc)), STEEL_KG_M3),
        Part(
            "face",
            g.frustum_between((0, by / 2, zc), (0, by / 2 + p["face_length"], zc), 0.5 * d, 0.46 * d),
            STEEL_KG_M3,
        ),
    ]
    # Claw: tapers from the eye block to a thin blade curled towards the handle.
    y_tip = -by / 2 - p["claw_length"]
    x_tip = -p["claw_curl"]
    claw = np.array(
        [[sx * d / 2, -by / 2, zc + sz * d / 2] for sx in (-1, 1) for sz in (-1, 1)]
        + [[x_tip + sx * 2.5 * MM, y_tip, zc + sz * 0.4 * d] for sx in (-1, 1) for sz in (-1, 1)]
    )
    parts.append(Part("claw", g.hull(claw), STEEL_KG_M3))
    parts.append(
        Part("shaft", g.box((shaft_len, w, t), (x_shaft - shaft_len / 2, 0, zc)), density)
    )
    parts.append(
        Part("grip", g.box((grip_len, gw, gt), (x_shaft - shaft_len - grip_len / 2, 0, zc)), density)
    )
    return parts


# ----------------------------------------------------------------------------
# bottle: standing PET bottle. 0.33-1 L bottles are 55-75 mm wide (1 L is
# ~75-80 mm) and 170-280 mm tall, with a 25-28 mm neck finish and cap.


def _sample_bottle(rng: np.random.Generator) -> Params:
    height = _u(rng, 170, 280) * MM
    return {
        "radius": _u(rng, 27.5, 37.5) * MM,
        "height": height,
        "base_height": _u(rng, 6, 12) * MM,
        "base_taper": _u(rng, 0.88, 0.95),
        "shoulder_height": _u(rng, 0.15, 0.26) * height,
        "shoulder_bulge": _u(rng, 0.6, 0.8),
        "neck_radius": _u(rng, 11.5, 14) * MM,
        "neck_length": _u(rng, 10, 22) * MM,
        "cap_extra": _u(rng, 1.0, 2.5) * MM,
        "cap_height": _u(rng, 11, 19) * MM,
    }


def _build_bottle(p: Params, density: float) -> list[Part]:
    r, h, rn = p["radius"], p["height"], p["neck_radius"]
    z_cap = h - p["cap_height"]
    z_neck = z_cap - p["neck_length"]
    z_shoulder = z_neck - p["shoulder_height"]
    z_base = p["base_height"]
    z_mid = z_shoulder + 0.45 * p["shoulder_height"]
    r_mid = rn + (r - rn) * p["shoulder_bulge"]
    return [
        Part("base", g.frustum_z(r * p["base_taper"], r, 0.0, z_base), density),
        Part("body", g.cylinder_z(r, z_base, z_shoulder), density),
        Part("shoulder_low", g.frustum_z(r, r_mid, z_shoulder, z_mid), density),
        Part("shoulder_high", g.frustum_z(r_mid, rn, z_mid, z_neck), density),
        Part("neck", g.cylinder_z(rn, z_neck, z_cap), density),
        Part("cap", g.cylinder_z(rn + p["cap_extra"], z_cap, h), density),
    ]


# ----------------------------------------------------------------------------
# tetra_pak: drink cartons. Tetra Brik 200 mL ~ 40 x 53 x 105 mm, 500 mL
# ~ 64 x 64 x 135 mm, 1 L ~ 64-70 x 95 x 195 mm; gable-top 0.5-1 L cartons
# have a 55-70 mm square footprint and are 150-240 mm tall with the roof.


def _sample_tetra_pak(rng: np.random.Generator) -> Params:
    size = _u(rng, 0.0, 1.0)
    gable = bool(rng.random() < 0.35)
    if gable:
        side = _u(rng, 55, 70) * MM
        return {
            "gable": 1.0,
            "length": side,
            "width": side,
            "height": _u(rng, 120, 190) * MM,
            "roof": _u(rng, 0.35, 0.45) * side,
            "fin_thickness": _u(rng, 3, 5) * MM,
            "fin_height": _u(rng, 10, 18) * MM,
        }
    return {
        "gable": 0.0,
        "length": (50 + 45 * size + _u(rng, -4, 4)) * MM,
        "width": min(70.0, 38 + 30 * size + _u(rng, -3, 3)) * MM,
        "height": (100 + 95 * size + _u(rng, -8, 8)) * MM,
        "fin_thickness": _u(rng, 3, 5) * MM,
        "fin_height": _u(rng, 4, 8) * MM,
        "cap": 1.0 if size > 0.35 and rng.random() < 0.7 else 0.0,
        "cap_radius": _u(rng, 10, 13) * MM,
        "cap_height": _u(rng, 8, 13) * MM,
    }


def _build_tetra_pak(p: Params, density: float) -> list[Part]:
    a, b, h = p["length"], p["width"], p["height"]
    ft, fh = p["fin_thickness"], p["fin_height"]
    parts = [Part("carton", g.box((a, b, h), (0, 0, h / 2)), density)]
    if p["gable"]:
        ridge = h + p["roof"]
        roof = [[sx * a / 2, sy * b / 2, h] for sx in (-1, 1) for sy in (-1, 1)]
        roof += [[sx * a / 2, 0.0, ridge] for sx in (-1, 1)]
        parts.append(Part("roof", g.hull(np.array(roof)), density))
        # The fin dips 2 mm into the roof so it is attached along the ridge.
        fin_h = fh + 2 * MM
        parts.append(Part("fin", g.box((a, ft, fin_h), (0, 0, ridge - 2 * MM + fin_h / 2)), density))
        return parts
    # Brick: sealed top seam folded along the short side, optional screw cap.
    parts.append(Part("seam", g.box((ft, b, fh), (-a / 2 + 6 * MM + ft / 2, 0, h + fh / 2)), density))
    if p["cap"]:
        rc = p["cap_radius"]
        cap = g.cylinder_z(rc, h, h + p["cap_height"], (a / 2 - rc - 5 * MM, 0.0))
        parts.append(Part("cap", cap, density))
    return parts


# ----------------------------------------------------------------------------
# flashlight: lying along x. 2xAA to 2xC torches: body 20-35 mm diameter,
# 120-230 mm long, head up to 50 mm; 0.05-0.4 kg with batteries.


def _sample_flashlight(rng: np.random.Generator) -> Params:
    r = _u(rng, 10, 17.5) * MM
    return {
        "radius": r,
        "body_length": _u(rng, 80, 160) * MM,
        "head_radius": min(r + _u(rng, 3, 10) * MM, 25 * MM),
        "head_length": _u(rng, 22, 42) * MM,
        "taper_length": _u(rng, 8, 22) * MM,
        "tail_radius": r * _u(rng, 1.0, 1.12),
        "tail_length": _u(rng, 8, 18) * MM,
        "button": 1.0 if rng.random() < 0.5 else 0.0,
        "button_length": _u(rng, 8, 14) * MM,
        "button_width": _u(rng, 6, 10) * MM,
        "button_height": _u(rng, 2, 4) * MM,
    }


def _build_flashlight(p: Params, density: float) -> list[Part]:
    r, rh, rt = p["radius"], p["head_radius"], p["tail_radius"]
    zc = max(rh, rt)
    x = np.cumsum([0.0, p["tail_length"], p["body_length"], p["taper_length"], p["head_length"]])

    def seg(i: int, r0: float, r1: float) -> trimesh.Trimesh:
        return g.frustum_between((x[i], 0, zc), (x[i + 1], 0, zc), r0, r1)

    parts = [
        Part("tail", seg(0, rt, rt), density),
        Part("body", seg(1, r, r), density),
        Part("taper", seg(2, r, rh), density),
        Part("head", seg(3, rh, rh), density),
    ]
    if p["button"]:
        bl, bw, bh = p["button_length"], p["button_width"], p["button_height"]
        xb = x[2] - 0.2 * p["body_length"]
        # Sunk 1 mm into the body so the button is attached to it.
        button = g.box((bl, bw, bh + MM), (xb, 0, zc + r - MM + (bh + MM) / 2))
        parts.append(Part("button", button, density))
    return parts


# ----------------------------------------------------------------------------
# camera: compact / small mirrorless, standing, lens towards -y. Bodies are
# 95-130 mm wide, 55-80 mm tall, 25-42 mm deep; lenses 32-64 mm diameter
# protrude 12-38 mm; 0.15-0.5 kg. Depth + lens is kept <= 75 mm.


def _sample_camera(rng: np.random.Generator) -> Params:
    width = _u(rng, 95, 130) * MM
    height = _u(rng, 55, 80) * MM
    depth = _u(rng, 25, 42) * MM
    lens_r = _u(rng, 16, min(32, height / MM / 2 - 3)) * MM
    protrusion = _u(rng, 12, min(38, 75 - depth / MM)) * MM
    grip_w = _u(rng, 15, 25) * MM
    # The lens must clear the grip (if it fits) and the body edges.
    lo = -width / 2 + lens_r + 3 * MM
    hi = width / 2 - grip_w - lens_r - 3 * MM
    grip = 1.0 if hi >= lo else 0.0
    if not grip:
        hi = width / 2 - lens_r - 3 * MM
    lens_x = _u(rng, lo, hi)
    hump_w = _u(rng, 28, 42) * MM
    button_r = _u(rng, 4, 6) * MM
    button_x = width / 2 - 12 * MM
    hump = 1.0 if rng.random() < 0.5 and lens_x + hump_w / 2 < button_x - button_r - 2 * MM else 0.0
    return {
        "width": width,
        "height": height,
        "depth": depth,
        "lens_radius": lens_r,
        "lens_protrusion": protrusion,
        "lens_x": lens_x,
        "grip": grip,
        "grip_width": grip_w,
        "grip_depth": _u(rng, 4, 10) * MM,
        "grip_height": _u(rng, 0.75, 0.9) * height,
        "button_radius": button_r,
        "button_height": _u(rng, 2.5, 4.5) * MM,
        "button_x": button_x,
        "hump": hump,
        "hump_width": hump_w,
        "hump_height": _u(rng, 10, 18) * MM,
    }


def _build_camera(p: Params, density: float) -> list[Part]:
    w, h, d = p["width"], p["height"], p["depth"]
    rl, pr, xl = p["lens_radius"], p["lens_protrusion"], p["lens_x"]
    zl = h / 2
    y0, y1, y2 = -d / 2, -d / 2 - 0.7 * pr, -d / 2 - pr
    parts = [
        Part("body", g.box((w, d, h), (0, 0, h / 2)), density),
        Part("lens_barrel", g.frustum_between((xl, y0, zl), (xl, y1, zl), rl, rl), density),
        Part("lens_front", g.frustum_between((xl, y1, zl), (xl, y2, zl), 0.97 * rl, 0.9 * rl), density),
        Part(
            "shutter",
            g.cylinder_z(p["button_radius"], h, h + p["button_height"], (p["button_x"], 0.0)),
            density,
        ),
    ]
    if p["grip"]:
        gw, gd, gh = p["grip_width"], p["grip_depth"], p["grip_height"]
        grip = g.box((gw, gd, gh), (w / 2 - gw / 2, -d / 2 - gd / 2, h / 2))
        parts.append(Part("grip", grip, density))
    if p["hump"]:
        hw, hh = p["hump_width"], p["hump_height"]
        pts = [[xl + sx * hw / 2, sy * 0.45 * d, h] for sx in (-1, 1) for sy in (-1, 1)]
        pts += [[xl + sx * 0.3 * hw, sy * 0.35 * d, h + hh] for sx in (-1, 1) for sy in (-1, 1)]
        parts.append(Part("viewfinder", g.hull(np.array(pts)), density))
    return parts


# ----------------------------------------------------------------------------
# can: sealed, full drink or food can. 250 mL slim: 53 x 134 mm; 330 mL:
# 66 x 115 mm; 500 mL: 66 x 168 mm; 400 g food can: 73 x 110 mm (width
# capped at 70 mm). Full cans weigh 0.27-0.45 kg.


def _sample_can(rng: np.random.Generator) -> Params:
    return {
        "radius": _u(rng, 26, 35) * MM,
        "height": _u(rng, 95, 160) * MM,
        "food": 1.0 if rng.random() < 0.35 else 0.0,
        "bottom_taper": _u(rng, 0.82, 0.9),
        "bottom_height": _u(rng, 4, 8) * MM,
        "top_taper": _u(rng, 0.86, 0.92),
        "top_height": _u(rng, 6, 12) * MM,
        "rim_height": _u(rng, 2, 3.5) * MM,
    }


def _build_can(p: Params, density: float) -> list[Part]:
    r, h, rim = p["radius"], p["height"], p["rim_height"]
    if p["food"]:
        # Food can: rolled rims slightly wider than the body.
        return [
            Part("bottom_rim", g.cylinder_z(r, 0.0, rim), density),
            Part("body", g.cylinder_z(0.985 * r, rim, h - rim), density),
            Part("top_rim", g.cylinder_z(r, h - rim, h), density),
        ]
    zb = p["bottom_height"]
    zt = h - rim - p["top_height"]
    r_top = r * p["top_taper"]
    return [
        Part("bottom", g.frustum_z(r * p["bottom_taper"], r, 0.0, zb), density),
        Part("body", g.cylinder_z(r, zb, zt), density),
        Part("neck", g.frustum_z(r, r_top, zt, h - rim), density),
        Part("rim", g.cylinder_z(0.98 * r_top, h - rim, h), density),
    ]


# ----------------------------------------------------------------------------
# apple: 58-75 mm wide (US "medium" is ~70-75 mm), height 0.8-0.95 of the
# width, widest above the middle; 0.07-0.2 kg (apples float: ~0.83 g/cm^3).


def _sample_apple(rng: np.random.Generator) -> Params:
    width = _u(rng, 58, 75) * MM
    return {
        "radius_x": width / 2,
        "radius_y": width / 2 * _u(rng, 0.93, 1.0),
        "height": width * _u(rng, 0.8, 0.95),
        "widest_at": _u(rng, 0.5, 0.62),
        "lean": _u(rng, -3, 3) * MM,
        "stem_radius": _u(rng, 1.5, 2.5) * MM,
        "stem_length": _u(rng, 7, 14) * MM,
        "stem_tilt_x": _u(rng, -3, 3) * MM,
        "stem_tilt_y": _u(rng, -3, 3) * MM,
    }


def _build_apple(p: Params, density: float) -> list[Part]:
    h, u0 = p["height"], p["widest_at"]
    rings = []
    for u in np.linspace(0.0, 1.0, 11):
        span = u0 if u < u0 else 1.0 - u0
        rho = max((1.0 - abs((u - u0) / span) ** 2.2) ** (1 / 2.2), 0.3 if u < u0 else 0.22)
        c = g.circle(1.0, 20)
        x = p["radius_x"] * rho * c[:, 0] + p["lean"] * u
        rings.append(np.column_stack([x, p["radius_y"] * rho * c[:, 1], np.full(20, u * h)]))
    top = np.array([p["lean"], 0.0, h])
    stem_top = top + np.array([p["stem_tilt_x"], p["stem_tilt_y"], p["stem_length"]])
    # The stem starts 1.5 mm inside the flat top so it is attached.
    stem = g.frustum_between(
        top - [0, 0, 1.5 * MM], stem_top, p["stem_radius"], 0.8 * p["stem_radius"], sections=8
    )
    return [Part("flesh", g.hull(np.vstack(rings)), density), Part("stem", stem, density)]


# ----------------------------------------------------------------------------
# toy_car: on its wheels. 1:43-1:24 toy cars are 90-190 mm long, 40-80 mm
# wide (width capped at 70 mm), 0.03-0.3 kg (mixed die-cast / plastic).


def _sample_toy_car(rng: np.random.Generator) -> Params:
    length = _u(rng, 90, 170) * MM
    return {
        "length": length,
        "width": min(length * _u(rng, 0.4, 0.5), 70 * MM),
        "wheel_radius": length * _u(rng, 0.09, 0.13),
        "wheel_width_frac": _u(rng, 0.14, 0.2),
        "clearance_frac": _u(rng, 0.45, 0.7),
        "body_height": length * _u(rng, 0.14, 0.2),
        "wheel_inset_frac": _u(rng, 1.2, 1.6),
        "cabin_length": length * _u(rng, 0.45, 0.6),
        "cabin_offset": length * _u(rng, -0.12, 0.05),
        "cabin_height": length * _u(rng, 0.1, 0.16),
        "windscreen_frac": _u(rng, 0.15, 0.3),
    }


def _build_toy_car(p: Params, density: float) -> list[Part]:
    length, width, rw = p["length"], p["width"], p["wheel_radius"]
    ww = p["wheel_width_frac"] * width
    wb = width - 2 * ww  # wheels sit outside the body and touch its sides
    z0 = rw * p["clearance_frac"]
    z1 = z0 + p["body_height"]
    parts = [Part("body", g.box((length, wb, z1 - z0), (0, 0, (z0 + z1) / 2)), density)]
    cl, cx, ch = p["cabin_length"], p["cabin_offset"], p["cabin_height"]
    front = p["windscreen_frac"] * cl
    cabin = [[cx + sx * cl / 2, sy * 0.46 * wb, z1] for sx in (-1, 1) for sy in (-1, 1)]
    roof_x = (cx - cl / 2 + 0.1 * cl, cx + cl / 2 - front)
    cabin += [[x, sy * 0.38 * wb, z1 + ch] for x in roof_x for sy in (-1, 1)]
    parts.append(Part("cabin", g.hull(np.array(cabin)), density))
    x_axle = length / 2 - rw * p["wheel_inset_frac"]
    for i, (sx, sy) in enumerate([(1, 1), (1, -1), (-1, 1), (-1, -1)]):
        y_in, y_out = sy * wb / 2, sy * (wb / 2 + ww)
        wheel = g.frustum_between((sx * x_axle, y_in, rw), (sx * x_axle, y_out, rw), rw, rw, sections=20)
        parts.append(Part(f"wheel_{i}", wheel, density))
    return parts


# ----------------------------------------------------------------------------
# banana: lying on its side, curved in the table plane. Bananas are 150-230
# mm along the curve and 32-42 mm thick; 0.1-0.22 kg with peel (~0.95 g/cm^3).
# The cross-section is a hexagon with a flat face down: bananas are ridged,
# and a round tube with tapered ends rolls on the table instead of resting.

BANANA_SEGMENTS = 5
BANANA_SIDES = 6


def _sample_banana(rng: np.random.Generator) -> Params:
    return {
        "length": _u(rng, 150, 210) * MM,
        "radius": _u(rng, 18, 23) * MM,  # hexagon circumradius
        "bend": np.deg2rad(_u(rng, 35, 70)),
        "taper_power": _u(rng, 0.3, 0.5),
        "stalk_length": _u(rng, 12, 22) * MM,
        "stalk_radius": _u(rng, 4, 6) * MM,
    }


def _build_banana(p: Params, density: float) -> list[Part]:
    length, rm, bend = p["length"], p["radius"], p["bend"]
    bend_radius = length / bend
    s = np.linspace(0.0, 1.0, BANANA_SEGMENTS + 1)
    theta = (s - 0.5) * bend
    centres = np.column_stack(
        [bend_radius * np.sin(theta), bend_radius * (1 - np.cos(theta)), np.full(len(s), rm)]
    )
    tangents = np.column_stack([np.cos(theta), np.sin(theta), np.zeros(len(s))])
    radii = rm * np.maximum(np.sin(np.pi * s) ** p["taper_power"], 0.28)
    # Consecutive segments share a ring (normal to the curve), so they touch
    # without overlapping.
    parts = []
    for k in range(BANANA_SEGMENTS):
        c0, c1, t0, t1 = centres[k], centres[k + 1], tangents[k], tangents[k + 1]
        segment = g.frustum_between(c0, c1, radii[k], radii[k + 1], t0, t1, BANANA_SIDES)
        parts.append(Part(f"segment_{k}", segment, density))
    stalk_end = centres[0] - p["stalk_length"] * tangents[0]
    rs = p["stalk_radius"]
    stalk = g.frustum_between(centres[0] + 1 * MM * tangents[0], stalk_end, rs, 0.8 * rs, sections=8)
    parts.append(Part("stalk", stalk, density))
    return parts


# category name -> (parameter sampler, parts builder)
SHAPES = {
    "mug": (_sample_mug, _build_mug),
    "hammer": (_sample_hammer, _build_hammer),
    "bottle": (_sample_bottle, _build_bottle),
    "tetra_pak": (_sample_tetra_pak, _build_tetra_pak),
    "flashlight": (_sample_flashlight, _build_flashlight),
    "camera": (_sample_camera, _build_camera),
    "can": (_sample_can, _build_can),
    "apple": (_sample_apple, _build_apple),
    "toy_car": (_sample_toy_car, _build_toy_car),
    "banana": (_sample_banana, _build_banana),
}
