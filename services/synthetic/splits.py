"""Splits, variants and conditions of the synthetic demonstrations, and their partitions.

What the evaluation enumerates (docs/synthetic.md#splits):

- :data:`OBJECTS_BY_SPLIT`: ``paper`` (the ICRA-25 dataset's ten objects) and ``household``
  (:mod:`services.synthetic.household`);
- :data:`VARIANTS`: ``cut`` (the stream is the manipulation), ``whole``, ``sequence`` (only the
  objects of :data:`SEQUENCE_OBJECTS`) and ``regrasp``;
- conditions: an idle second hand (:data:`IDLE_HAND_LABELS`) and a detection gap
  (:data:`GAPS`); :data:`CONDITIONS` names the combinations the evaluation reports;
- :data:`FREE_OBJECT`: the 60 s hand-only stream (no contact at all).

Partitions, as the paper did: by participant, so no demonstration is in both. Paper: tuning on
four objects by participants 1 and 2, evaluation on all ten by participant 3. Household: tuning
on one object of each kind by participants 4 and 5, evaluation on all household objects by
participants 6 and 7 (5 and 7 are left-handed). Seeds: any; the participant and the seed both
enter every random stream, so tuning and evaluation never share a draw.
"""

from __future__ import annotations

from dataclasses import dataclass

from services.synthetic.household import HOUSEHOLD_OBJECTS, HOUSEHOLD_PRESETS, SEQUENCE_PARTNERS
from services.synthetic.objects import OBJECTS, PRESETS, ObjectPreset

# The paper (section IV.A.3): tuning on four objects by participants 1 and 2, evaluation on all
# ten by participant 3.
TUNING_OBJECTS: tuple[str, ...] = ("valve", "tension_belt", "window_lock", "flap_latch")
TUNING_SPLIT: list[tuple[str, int]] = [(o, p) for o in TUNING_OBJECTS for p in (1, 2)]
EVALUATION_SPLIT: list[tuple[str, int]] = [(o, 3) for o in OBJECTS]

SPLITS: tuple[str, ...] = ("paper", "household")
OBJECTS_BY_SPLIT: dict[str, tuple[str, ...]] = {"paper": OBJECTS, "household": HOUSEHOLD_OBJECTS}
VARIANTS: tuple[str, ...] = ("cut", "whole", "sequence", "regrasp")
SEQUENCE_OBJECTS: dict[str, tuple[str, ...]] = {
    split: tuple(o for o in objects if o in SEQUENCE_PARTNERS)
    for split, objects in OBJECTS_BY_SPLIT.items()}
IDLE_HAND_LABELS: tuple[str, ...] = ("opposite", "same", "flipping")
GAPS: tuple[str, ...] = ("dropout", "regrasp")
HANDS: tuple[str, ...] = ("left", "right")
FREE_OBJECT = "free"
STILL_HOLDS: tuple[str, ...] = tuple(o for o, p in HOUSEHOLD_PRESETS.items()
                                     if p.joint_type == "rigid")

# Named conditions: keyword arguments of generate() beside the variant.
CONDITIONS: dict[str, dict[str, str]] = {
    "plain": {},
    "idle_opposite": {"idle_hand": "opposite"},
    "idle_same": {"idle_hand": "same"},
    "idle_flipping": {"idle_hand": "flipping"},
    "dropout": {"gap": "dropout"},
    "regrasp_gap": {"gap": "regrasp"},
}

HOUSEHOLD_TUNING_OBJECTS: tuple[str, ...] = (
    "cabinet_door", "box_lid", "pull_down_lever", "stove_knob", "kitchen_drawer", "slide_latch",
    "hold_handle")
HOUSEHOLD_TUNING_SPLIT: list[tuple[str, int]] = [
    (o, p) for o in HOUSEHOLD_TUNING_OBJECTS for p in (4, 5)]
HOUSEHOLD_EVALUATION_SPLIT: list[tuple[str, int]] = [
    (o, p) for o in HOUSEHOLD_OBJECTS for p in (6, 7)]

TUNING_BY_SPLIT: dict[str, list[tuple[str, int]]] = {
    "paper": TUNING_SPLIT, "household": HOUSEHOLD_TUNING_SPLIT}
EVALUATION_BY_SPLIT: dict[str, list[tuple[str, int]]] = {
    "paper": EVALUATION_SPLIT, "household": HOUSEHOLD_EVALUATION_SPLIT}
# Every participant of some split (the command line offers these).
PARTICIPANTS: tuple[int, ...] = tuple(sorted(
    {p for pairs in (*TUNING_BY_SPLIT.values(), *EVALUATION_BY_SPLIT.values()) for _, p in pairs}))
FREE_TUNING: list[tuple[str, int]] = [(FREE_OBJECT, 4), (FREE_OBJECT, 5)]
FREE_EVALUATION: list[tuple[str, int]] = [(FREE_OBJECT, 6), (FREE_OBJECT, 7)]


def preset(name: str) -> ObjectPreset:
    """The preset of any split's object ``name``; ``ValueError`` naming the known ones."""
    if name in PRESETS:
        return PRESETS[name]
    if name in HOUSEHOLD_PRESETS:
        return HOUSEHOLD_PRESETS[name]
    known = ", ".join((*OBJECTS, *HOUSEHOLD_OBJECTS))
    raise ValueError(f"unknown object {name!r}; known: {known}, {FREE_OBJECT}")


def split_of(name: str) -> str:
    """The split that ``name`` belongs to ("paper", "household" or "free")."""
    if name == FREE_OBJECT:
        return "free"
    for split, objects in OBJECTS_BY_SPLIT.items():
        if name in objects:
            return split
    preset(name)  # raises with the known names
    raise AssertionError("unreachable")


def variants_of(name: str) -> tuple[str, ...]:
    """The variants ``name`` can be generated in."""
    if name == FREE_OBJECT:
        return ("free",)
    split_of(name)
    return tuple(v for v in VARIANTS if v != "sequence" or name in SEQUENCE_PARTNERS)


def check_request(object_name: str, variant: str, idle_hand: str | None, gap: str | None,
                  hand: str | None) -> None:
    """``ValueError`` naming what is wrong with a generate() request."""
    if object_name == FREE_OBJECT:
        if variant not in ("cut", "free") or gap is not None or idle_hand is not None:
            raise ValueError("the free stream takes no variant, gap or idle hand")
    elif variant not in variants_of(object_name):
        raise ValueError(f"{object_name!r} has no variant {variant!r}; "
                         f"choose from {', '.join(variants_of(object_name))}")
    if idle_hand is not None and idle_hand not in IDLE_HAND_LABELS:
        raise ValueError(f"idle_hand must be one of {IDLE_HAND_LABELS}, got {idle_hand!r}")
    if gap is not None:
        if gap not in GAPS:
            raise ValueError(f"gap must be one of {GAPS}, got {gap!r}")
        if variant not in ("cut", "whole"):
            raise ValueError(f"a gap applies to the cut and whole variants, not {variant!r}")
    if hand is not None and hand not in HANDS:
        raise ValueError(f"hand must be 'left' or 'right', got {hand!r}")


@dataclass(frozen=True)
class DemoSpec:
    """One demonstration to generate: ``generate(**spec.kwargs())``."""

    object_name: str
    participant: int
    seed: int
    variant: str = "cut"
    idle_hand: str | None = None
    gap: str | None = None

    def kwargs(self) -> dict[str, object]:
        """Keyword arguments of :func:`services.synthetic.generator.generate`."""
        return {"object_name": self.object_name, "participant": self.participant,
                "seed": self.seed, "variant": self.variant, "idle_hand": self.idle_hand,
                "gap": self.gap}


def demo_specs(split: str, partition: str = "evaluation", seeds: int = 1, variant: str = "cut",
               condition: str = "plain") -> list[DemoSpec]:
    """Every demonstration of ``split``'s ``partition`` ("tuning"/"evaluation") in ``variant``
    and ``condition`` (a key of :data:`CONDITIONS`), seeds ``0 .. seeds - 1``.

    ``sequence`` keeps only the objects that have one; a gap condition keeps only the ``cut``
    and ``whole`` variants (empty list otherwise); ``split == "free"`` lists the free streams.
    """
    if partition not in ("tuning", "evaluation"):
        raise ValueError(f"partition must be 'tuning' or 'evaluation', got {partition!r}")
    if condition not in CONDITIONS:
        raise ValueError(f"unknown condition {condition!r}; known: {', '.join(CONDITIONS)}")
    if split == "free":
        pairs = FREE_TUNING if partition == "tuning" else FREE_EVALUATION
        return [DemoSpec(o, p, s, "cut") for o, p in pairs for s in range(seeds)]
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; known: {', '.join(SPLITS)}, free")
    cond = CONDITIONS[condition]
    if "gap" in cond and variant not in ("cut", "whole"):
        return []
    pairs = (TUNING_BY_SPLIT if partition == "tuning" else EVALUATION_BY_SPLIT)[split]
    return [DemoSpec(o, p, s, variant, cond.get("idle_hand"), cond.get("gap"))
            for o, p in pairs if variant in variants_of(o) for s in range(seeds)]
