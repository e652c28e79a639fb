"""The ``household`` split: everyday articulated objects beyond the paper's ten, and still holds.

Frames and fields as in :mod:`services.synthetic.objects` (object frame ``o``: x right, y out of
the mounting surface towards the person and the camera, z up; SI units). Sizes are plausible
values for common furniture and fittings, chosen once and not tuned to any estimator; ``radius``
below is the grasp point's distance from a revolute axis, ``stroke`` the grasp point's path
length over the nominal range (both before the per-demonstration spreads: ``scale_spread`` on the
size, ``range_spread`` and the participant's range factor on the range).

===============  ====  ===================  ==========  ============  =========  ======  =======
name             type  axis (o)             radius [m]  range         grasp      stroke  camera
===============  ====  ===================  ==========  ============  =========  ======  =======
cabinet_door     R     +z (hinge left)      0.30 +-15%  1.1 rad       power      0.33 m  0.8-1.5
wardrobe_door    R     -z (hinge right)     0.38 +-5%   0.95 rad      hook       0.36 m  1.0-1.8
oven_door        R     -x (hinge bottom)    0.39        1.0 rad       power      0.39 m  0.9-1.6
box_lid          R     +x (hinge back)      0.21 +-10%  1.5 rad       pinch      0.32 m  0.6-1.2
chest_lid        R     +x (hinge back)      0.39        1.0 rad       hook       0.39 m  1.0-1.7
pull_down_lever  R     -x (pivot on wall)   0.20 +-20%  1.4 rad       power      0.28 m  0.6-1.2
door_lever       R     +y (to the camera)   0.09 +-10%  0.7 rad       power      0.06 m  0.5-1.0
faucet_lever     R     +x (lift)            0.09 +-15%  0.5 rad       pinch      0.05 m  0.5-1.0
faucet_swing     R     +z (swing)           0.09 +-15%  0.8 rad       power      0.07 m  0.5-1.0
stove_knob       R     +y (to the camera)   0.008       2.0 rad       key_pinch  0.016 m 0.5-1.0
small_dial       R     +y (to the camera)   0.005       2.8 rad       tripod     0.014 m 0.4-0.9
round_dial       R     +y (to the camera)   0.025       1.2 rad       pinch      0.03 m  0.4-0.9
lift_latch       R     -y (to the wall)     0.07        0.7 rad       pinch      0.05 m  0.5-1.0
kitchen_drawer   P     +y (to the camera)   --          0.38 m        power      0.38 m  0.7-1.4
desk_drawer      P     +y (to the camera)   --          0.15 m        pinch      0.15 m  0.5-1.0
sliding_door     P     -x                   --          0.40 m        hook       0.40 m  1.0-1.8
slide_latch      P     +x                   --          0.03 m        pinch      0.03 m  0.4-0.9
sash_window      P     +z (up)              --          0.25 m        hook       0.25 m  0.8-1.5
hold_handle      rigid fixed bar handle     --          held 3-5 s    power      --      0.5-1.2
hold_knob        rigid fixed knob           --          held 3-5 s    pinch      --      0.4-1.0
===============  ====  ===================  ==========  ============  =========  ======  =======

Knobs, dials and the door lever turn about an axis within ~30 deg of the viewing direction
(``_FACING`` viewpoints). Drawers, the oven door, the cabinet and wardrobe doors and the pull-down
lever move towards the camera; their return strokes and the lids move away from it. Hand speeds
reach ~1 m/s on the long strokes (the kitchen drawer's 0.38 m in ~0.6-1.0 s: min-jerk peak
1.875 x mean speed).

The second joints of the ``sequence`` variant (:data:`SEQUENCE_PARTNERS`): a slide bolt on the
cabinet door (latch, then door), a clasp on the box front (lock, then lid), a thumb-turn lock on
the sliding door (lock, then slide), the door that the paper's barrel bolt locks (bolt, then
door) and the lid lock of the paper's travel mug (lock, then lid).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.synthetic.objects import ObjectPreset


def _unit(*v: float) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=float)
    a = a / np.linalg.norm(a)
    return (float(a[0]), float(a[1]), float(a[2]))


_WALL = ((0.0, 35.0), (-45.0, 45.0))
_TABLE = ((25.0, 60.0), (-45.0, 45.0))
_LOW = ((10.0, 45.0), (-40.0, 40.0))     # appliances below eye level: camera looks down a bit
_FACING = ((0.0, 20.0), (-20.0, 20.0))   # the camera faces the surface: axis near the view ray


def _p(name: str, joint_type: str, axis: tuple[float, float, float],
       point: tuple[float, float, float], range_nominal: float, range_spread: float,
       grasp: tuple[float, float, float], grasp_type: str, distal: tuple[float, float, float],
       radial: tuple[float, float, float], occlusion: float, stroke_s: float,
       view: tuple[tuple[float, float], tuple[float, float]], camera: tuple[float, float],
       description: str, **extra: object) -> ObjectPreset:
    return ObjectPreset(
        name=name, joint_type=joint_type, axis=axis, point=point,  # type: ignore[arg-type]
        range_nominal=range_nominal, range_spread=range_spread, grasp=grasp,
        grasp_type=grasp_type, hand_distal=distal, hand_radial=radial,  # type: ignore[arg-type]
        occlusion=occlusion, stroke_duration_s=stroke_s, view_elevation_deg=view[0],
        view_azimuth_deg=view[1], camera_distance_m=camera, description=description,
        **extra)  # type: ignore[arg-type]


HOUSEHOLD_PRESETS: dict[str, ObjectPreset] = {
    p.name: p
    for p in (
        _p("cabinet_door", "revolute", (0.0, 0.0, 1.0), (0.0, 0.0, 0.0), 1.1, 0.12,
           (0.30, 0.045, 0.0), "power", _unit(-0.4, -1.0, 0.0), (0.0, 0.0, 1.0), 0.30, 1.4,
           _WALL, (0.8, 1.5), "kitchen cabinet door, bar handle 25-35 cm from the hinge",
           scale_spread=0.15),
        _p("wardrobe_door", "revolute", (0.0, 0.0, -1.0), (0.0, 0.0, 0.0), 0.95, 0.1,
           (-0.375, 0.02, 0.1), "hook", _unit(-1.0, -0.3, 0.0), (0.0, 0.0, 1.0), 0.35, 1.3,
           _WALL, (1.0, 1.8), "wardrobe door pulled open by its edge, hinge on the right",
           scale_spread=0.05),
        _p("oven_door", "revolute", (-1.0, 0.0, 0.0), (0.0, 0.0, 0.0), 1.0, 0.08,
           (0.0, 0.04, 0.39), "power", _unit(0.0, -0.5, -1.0), (1.0, 0.0, 0.0), 0.25, 1.5,
           _LOW, (0.9, 1.6), "oven door pulled down towards the person by its top bar"),
        _p("box_lid", "revolute", (1.0, 0.0, 0.0), (0.0, -0.20, 0.15), 1.5, 0.15,
           (0.0, 0.01, 0.16), "pinch", _unit(0.0, -1.0, -0.5), (1.0, 0.0, 0.0), 0.35, 1.4,
           _TABLE, (0.6, 1.2), "storage-box lid lifted by its front edge", scale_spread=0.1),
        _p("chest_lid", "revolute", (1.0, 0.0, 0.0), (0.0, -0.37, 0.45), 1.0, 0.1,
           (0.0, 0.02, 0.46), "hook", _unit(0.0, -1.0, 0.2), (-1.0, 0.0, 0.0), 0.40, 1.6,
           _TABLE, (1.0, 1.7), "toy-chest lid lifted by fingers hooked under its front lip"),
        _p("pull_down_lever", "revolute", (-1.0, 0.0, 0.0), (0.0, 0.0, 0.0), 1.4, 0.12,
           (0.0, 0.03, 0.20), "power", _unit(0.3, -1.0, 0.0), (0.0, 0.0, 1.0), 0.30, 1.2,
           _WALL, (0.6, 1.2), "wall lever pulled from upright down towards the person",
           scale_spread=0.2),
        _p("door_lever", "revolute", (0.0, 1.0, 0.0), (0.0, 0.0, 0.0), 0.7, 0.15,
           (0.09, 0.06, 0.0), "power", _unit(0.0, -1.0, -0.6), (1.0, 0.0, 0.0), 0.35, 0.9,
           _FACING, (0.5, 1.0), "door lever handle pressed down; axis through the door",
           scale_spread=0.1),
        _p("faucet_lever", "revolute", (1.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.5, 0.2,
           (0.0, 0.09, 0.01), "pinch", _unit(0.0, -1.0, -0.3), (1.0, 0.0, 0.0), 0.35, 0.8,
           _TABLE, (0.5, 1.0), "single-lever mixer tap lifted by the lever tip",
           scale_spread=0.15),
        _p("faucet_swing", "revolute", (0.0, 0.0, 1.0), (0.0, 0.0, 0.0), 0.8, 0.2,
           (0.0, 0.09, 0.01), "power", _unit(0.0, -1.0, -0.4), (1.0, 0.0, 0.0), 0.30, 0.9,
           _TABLE, (0.5, 1.0), "mixer tap lever swung sideways (hot/cold)", scale_spread=0.15),
        _p("stove_knob", "revolute", (0.0, 1.0, 0.0), (0.0, 0.0, 0.0), 2.0, 0.15,
           (0.008, 0.03, 0.0), "key_pinch", _unit(0.2, -1.0, 0.3), (0.0, 0.0, 1.0), 0.40, 1.2,
           _FACING, (0.5, 1.0), "stove knob turned by its grip fin, 8 mm from the axis",
           ratchet=True),
        _p("small_dial", "revolute", (0.0, 1.0, 0.0), (0.0, 0.0, 0.0), 2.8, 0.1,
           (0.005, 0.04, 0.0), "tripod", _unit(0.0, -1.0, 0.2), (0.0, 0.0, 1.0), 0.45, 1.2,
           _FACING, (0.4, 0.9), "small timer dial turned with three fingertips", ratchet=True),
        _p("round_dial", "revolute", (0.0, 1.0, 0.0), (0.0, 0.0, 0.0), 1.2, 0.2,
           (0.025, 0.035, 0.0), "pinch", _unit(-0.3, -1.0, 0.0), (0.0, 0.0, 1.0), 0.35, 1.0,
           _FACING, (0.4, 0.9), "thermostat dial turned by its rim", ratchet=True),
        _p("lift_latch", "revolute", (0.0, -1.0, 0.0), (0.0, 0.0, 0.0), 0.7, 0.15,
           (0.07, 0.045, 0.0), "pinch", _unit(0.0, -1.0, -0.3), (1.0, 0.0, 0.0), 0.40, 0.8,
           _FACING, (0.5, 1.0), "gate latch bar lifted about its pivot"),
        _p("kitchen_drawer", "prismatic", (0.0, 1.0, 0.0), (0.0, 0.04, 0.0), 0.38, 0.15,
           (0.0, 0.04, 0.0), "power", _unit(0.0, -1.0, -0.6), (1.0, 0.0, 0.0), 0.25, 0.8,
           _LOW, (0.7, 1.4), "kitchen drawer pulled out by its bar handle, fast"),
        _p("desk_drawer", "prismatic", (0.0, 1.0, 0.0), (0.0, 0.025, 0.0), 0.15, 0.2,
           (0.0, 0.025, 0.0), "pinch", _unit(0.0, -1.0, 0.3), (1.0, 0.0, 0.0), 0.40, 0.9,
           _LOW, (0.5, 1.0), "desk drawer pulled by a small knob"),
        _p("sliding_door", "prismatic", (-1.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.40, 0.1,
           (0.0, 0.0, 0.0), "hook", _unit(0.4, -1.0, 0.0), (0.0, 0.0, 1.0), 0.50, 1.0,
           _WALL, (1.0, 1.8), "wardrobe sliding door pulled sideways by its finger recess"),
        _p("slide_latch", "prismatic", (1.0, 0.0, 0.0), (0.0, 0.02, 0.0), 0.03, 0.2,
           (0.0, 0.02, 0.0), "pinch", _unit(0.0, -1.0, 0.3), (1.0, 0.0, 0.0), 0.50, 0.7,
           _WALL, (0.4, 0.9), "3 cm sliding latch, knob pinched"),
        _p("sash_window", "prismatic", (0.0, 0.0, 1.0), (0.0, 0.03, 0.0), 0.25, 0.15,
           (0.0, 0.03, 0.0), "hook", _unit(0.0, -1.0, 0.2), (-1.0, 0.0, 0.0), 0.30, 1.3,
           _WALL, (0.8, 1.5), "sash window lifted by fingers hooked under its rail"),
        _p("hold_handle", "rigid", (1.0, 0.0, 0.0), (0.0, 0.04, 0.0), 0.0, 0.0,
           (0.0, 0.04, 0.0), "power", _unit(-0.4, -1.0, 0.0), (0.0, 0.0, 1.0), 0.30, 1.0,
           _WALL, (0.5, 1.2), "a fixed bar handle grasped and held still"),
        _p("hold_knob", "rigid", (1.0, 0.0, 0.0), (0.0, 0.03, 0.0), 0.0, 0.0,
           (0.0, 0.03, 0.0), "pinch", _unit(0.0, -1.0, 0.3), (1.0, 0.0, 0.0), 0.45, 1.0,
           _WALL, (0.4, 1.0), "a fixed knob pinched and held still"),
    )
}

HOUSEHOLD_OBJECTS: tuple[str, ...] = tuple(HOUSEHOLD_PRESETS)


@dataclass(frozen=True)
class SequencePartner:
    """The other joint of a two-joint object (``sequence`` variant), in the object's frame ``o``.

    ``preset`` is the partner joint; ``partner_first``: the partner is manipulated first (a lock
    before the split object's own joint) or second (the split object is the lock). ``mounted``:
    the first joint's part is carried by the second joint's part (a latch on a door), otherwise
    it sits on the fixed base.
    """

    preset: ObjectPreset
    partner_first: bool
    mounted: bool


SEQUENCE_PARTNERS: dict[str, SequencePartner] = {
    "cabinet_door": SequencePartner(
        _p("door_latch", "prismatic", (-1.0, 0.0, 0.0), (0.33, 0.02, 0.25), 0.03, 0.2,
           (0.33, 0.02, 0.25), "pinch", _unit(0.0, -1.0, 0.3), (1.0, 0.0, 0.0), 0.50, 0.8,
           _WALL, (0.8, 1.5), "slide bolt on the cabinet door"), partner_first=True,
        mounted=True),
    "box_lid": SequencePartner(
        _p("box_clasp", "revolute", (1.0, 0.0, 0.0), (0.0, 0.02, 0.13), 1.6, 0.15,
           (0.0, 0.035, 0.09), "pinch", _unit(0.0, -1.0, 0.4), (1.0, 0.0, 0.0), 0.40, 0.9,
           _TABLE, (0.6, 1.2), "clasp on the box front flipped up"), partner_first=True,
        mounted=False),
    "sliding_door": SequencePartner(
        _p("thumb_turn", "revolute", (0.0, 1.0, 0.0), (0.08, 0.0, 0.20), 1.57, 0.1,
           (0.092, 0.03, 0.20), "key_pinch", _unit(0.2, -1.0, 0.3), (0.0, 0.0, 1.0), 0.40, 1.0,
           _WALL, (1.0, 1.8), "thumb-turn lock on the sliding door"), partner_first=True,
        mounted=True),
    "bolt": SequencePartner(
        _p("bolt_door", "revolute", (0.0, 0.0, -1.0), (0.34, 0.0, 0.0), 0.9, 0.12,
           (-0.05, 0.04, -0.12), "power", _unit(0.4, -1.0, 0.0), (0.0, 0.0, 1.0), 0.30, 1.6,
           _WALL, (0.8, 1.6), "the door the barrel bolt locks, opened by its handle"),
        partner_first=False, mounted=True),
    "mug": SequencePartner(
        _p("mug_lock", "prismatic", (1.0, 0.0, 0.0), (0.0, 0.0, 0.172), 0.012, 0.1,
           (0.0, 0.0, 0.172), "pinch", _unit(0.0, -0.6, -1.0), (1.0, 0.0, 0.0), 0.40, 0.7,
           _TABLE, (0.4, 1.0), "slide lock on the travel-mug lid"), partner_first=True,
        mounted=True),
}
