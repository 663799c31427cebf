"""The grasp judge: an observer that decides from contacts whether a grasp held, and why not.

The judge is the only system of the episode Diagram with privileged ports (the plant's
contact results and body poses); policies see sensors only. It reads the phase of the
shared grasp motion from the policy's `control_status` output (`MOTION_PHASES`: approach,
descend, close, lift, hold, done) and samples the contacts every `JudgeConfig.period_s`
(10 ms; a Python system evaluated at every 2 ms plant step would cost real-time factor),
and only while something can be learned from them (descend to hold).

Success: when the motion is done (after the hold), an object touches both pads (the
2F-85's `left_finger` and `right_finger` bodies) and its lowest point is at least
`JudgeConfig.min_lift_m` above the table.

Failure classes (`drake_grasp.evaluation.records.GRASP_FAILURES`; each reason starts with its class):
    missed: no object touched both pads when the closing ended (also when the policy
        ended without closing the gripper; the policy's own reason is kept then).
    pushed-away: the object the grasp went for (the one nearest the grasp axis when the
        descent started) moved more than `max_push_m` (2 cm) horizontally between the
        start of the descent and the moment the closing pads first touched it (or the
        end of the closing, if they never did), and nothing was held.
    collision: a gripper body (finger, palm, housing) touched an object during the
        descent, before the closing started, and nothing was held (without a push).
    slipped-during-lift: an object was held after closing but, at the end of the lift
        (or earlier), it no longer touched both pads or was not lifted.
    slipped-during-hold: it was still held and lifted after the lift, not after the hold.
    timeout: the episode ended before the grasp motion was done.
The episode runner adds "simulation-error" when the simulation raises.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.multibody.plant import ContactResults
from pydrake.multibody.tree import BodyIndex
from pydrake.systems.framework import LeafSystem

from drake_grasp.config.sections import JudgeConfig
from drake_grasp.systems.state import shared_when_copied
from drake_grasp.systems.supervisor import MOTION_PHASES, motion_phase_name

# The bodies of the 2F-85 that carry the pads (models/robotiq_2f85).
PAD_BODIES = ("left_finger", "right_finger")


# --------------------------------------------------------------------------- contacts

def geometry_bodies(plant) -> dict[int, int]:
    """Collision geometry id (its integer value) -> index of the body it belongs to, for
    every body of a finalized plant registered with a SceneGraph."""
    out = {}
    for i in range(plant.num_bodies()):
        body = plant.get_body(BodyIndex(i))
        for gid in plant.GetCollisionGeometriesForBody(body):
            out[gid.get_value()] = int(body.index())
    return out


def body_contacts(contact_results: ContactResults, body_of_geometry) -> set[tuple[int, int]]:
    """Pairs (a, b), a < b, of body indices in contact: hydroelastic contact surfaces and
    point-pair contacts (hydroelastic with fallback produces both).

    Args:
        contact_results: the plant's `contact_results` output.
        body_of_geometry (Mapping[int, int] | Callable[[int], int]): collision geometry
            id value -> body index (`geometry_bodies`), or a callable doing the same.
    """
    lookup = body_of_geometry if callable(body_of_geometry) else body_of_geometry.__getitem__
    pairs = set()
    for i in range(contact_results.num_hydroelastic_contacts()):
        surface = contact_results.hydroelastic_contact_info(i).contact_surface()
        a = int(lookup(surface.id_M().get_value()))
        b = int(lookup(surface.id_N().get_value()))
        pairs.add((min(a, b), max(a, b)))
    for i in range(contact_results.num_point_pair_contacts()):
        info = contact_results.point_pair_contact_info(i)
        a, b = int(info.bodyA_index()), int(info.bodyB_index())
        pairs.add((min(a, b), max(a, b)))
    return pairs


def touching(pairs, body: int, others) -> set[int]:
    """Which of `others` (body indices) touch `body` in the contact `pairs`."""
    others = set(int(o) for o in others)
    out = set()
    for a, b in pairs:
        if a == body and b in others:
            out.add(b)
        elif b == body and a in others:
            out.add(a)
    return out


def pad_contacts(plant, plant_context, object_body, pad_bodies=PAD_BODIES) -> set[str]:
    """Names of the pad bodies the object touches, from the plant's contact results
    (hydroelastic or point contact). For code that holds the plant (the grasp lab); the
    `GraspJudge` reads the same from its input ports."""
    results = plant.get_contact_results_output_port().Eval(plant_context)
    names = {int(plant.get_body(BodyIndex(i)).index()): plant.get_body(BodyIndex(i)).name()
             for i in range(plant.num_bodies())
             if plant.get_body(BodyIndex(i)).name() in pad_bodies}
    pairs = body_contacts(results, geometry_bodies(plant))
    return {names[i] for i in touching(pairs, int(object_body.index()), names)}


def pad_squeeze_n(plant, plant_context, object_body, pad_bodies=PAD_BODIES) -> dict[str, float]:
    """Force each pad presses on the object along the pad's closing axis (its body x
    axis) [N], summed over their hydroelastic contact surfaces and point contacts; pads
    not touching it are left out. For code that holds the plant (the grasp lab)."""
    results = plant.get_contact_results_output_port().Eval(plant_context)
    bodies = geometry_bodies(plant)
    target = int(object_body.index())
    pads = {int(plant.GetBodyByName(name).index()): name for name in pad_bodies
            if plant.HasBodyNamed(name)}
    axes = {i: plant.EvalBodyPoseInWorld(plant_context, plant.get_body(BodyIndex(i)))
            .rotation().matrix()[:, 0] for i in pads}
    force = {}

    def add(a: int, b: int, f_on_a) -> None:
        # f_on_a: the force on body a; the pad's share is along its axis either way.
        if a in pads and b == target:
            force[pads[a]] = force.get(pads[a], 0.0) + abs(float(np.dot(f_on_a, axes[a])))
        elif b in pads and a == target:
            force[pads[b]] = force.get(pads[b], 0.0) + abs(float(np.dot(f_on_a, axes[b])))

    for i in range(results.num_hydroelastic_contacts()):
        info = results.hydroelastic_contact_info(i)
        surface = info.contact_surface()
        add(bodies[surface.id_M().get_value()], bodies[surface.id_N().get_value()],
            info.F_Ac_W().translational())
    for i in range(results.num_point_pair_contacts()):
        info = results.point_pair_contact_info(i)
        add(int(info.bodyA_index()), int(info.bodyB_index()), -info.contact_force())
    return force


# --------------------------------------------------------------------------- the judge

@dataclass(frozen=True)
class GraspJudgement:
    """The judge's verdict (the `judgement` output).

    Attributes:
        decided: the grasp motion was done when this was computed (else: timeout).
        attempted: the gripper closed (False when the policy gave up before closing).
        success: held and lifted after the hold.
        failure: "" on success, else one of `drake_grasp.evaluation.records.GRASP_FAILURES`.
        reason: None on success, else "<failure>: <what happened>".
        grasped_object_id: the object held and lifted at the end (None unless success).
        object_lowest_point_m: the lowest point above the table, at the end, of the
            object held after closing (else of the object the grasp went for).
        held_after_close: an object touched both pads when the closing ended.
        details: the contact history in numbers (phase start times, the targeted
            object, its push before the pads touched it, the first collision, ...).
    """

    decided: bool = False
    attempted: bool = False
    success: bool = False
    failure: str = "timeout"
    reason: str | None = None
    grasped_object_id: str | None = None
    object_lowest_point_m: float | None = None
    held_after_close: bool = False
    details: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)


@shared_when_copied
@dataclass(frozen=True)
class JudgeHistory:
    """What the judge has seen (the Context's abstract state)."""

    phase: str = "approach"
    phase_start_s: tuple = ()              # ((phase, time), ...) in the order seen
    descend_xy: tuple | None = None        # each object's (x, y) when the descent started
    target: int | None = None              # object nearest the grasp axis then
    push_m: float | None = None            # its horizontal move until the pads touched it
    pads_touched_target_s: float | None = None
    # (time, gripper body name, object index, names of every gripper body touching an
    # object then): the first sample with a touch; the name is the lowest-indexed body
    # touching the first object (base, left finger, right finger in the model's order), so
    # a touch by both fingers within one sample names the left: the names say which.
    collision: tuple | None = None
    closed: bool = False                   # the closing ended
    held: int | None = None                # object touching both pads when it ended
    lost: tuple | None = None              # (time, phase): the held object left a pad
    lift_end: tuple | None = None          # (both pads touched, lowest point) after the lift
    verdict: GraspJudgement | None = None


class GraspJudge(LeafSystem):
    """Decides success and the failure class of a grasp from the contact history.

    See the module docstring for the rules. State: a `JudgeHistory` (abstract), updated
    by a periodic unrestricted update every `config.period_s`.

    Input ports:
        contact_results: the plant's ContactResults.
        body_poses: the plant's body poses (std::vector<RigidTransform>).
        control_status: the policy's [control step, approaching, motion phase]; only the
            motion phase (`MOTION_PHASES` index) is read.
    Output ports:
        judgement: a `GraspJudgement` (abstract). Once the motion is done it is the
            verdict; before that, a "timeout" judgement naming the phase.
    """

    def __init__(self, *, config: JudgeConfig, object_bodies, object_ids, object_points,
                 gripper_bodies: dict, pad_bodies, grasp_body, X_BG: RigidTransform,
                 geometry_bodies: dict, table_z: float = 0.0):
        """
        Args:
            config: thresholds and the sampling period.
            object_bodies: body index of each scene object.
            object_ids: the objects' ids (for the verdict).
            object_points: per object, surface points (N, 3) in its body frame (for the
                lowest point and the object nearest the grasp axis).
            gripper_bodies: body index -> name of every gripper body (collision checks).
            pad_bodies: the two body indices that carry the pads.
            grasp_body: index of the body the grasp frame G is fixed to; X_BG its pose.
            geometry_bodies: collision geometry id value -> body index (`geometry_bodies`).
        """
        super().__init__()
        self._c = config
        self._objects = [int(b) for b in object_bodies]
        self._ids = list(object_ids)
        self._points = [np.asarray(P, float) for P in object_points]
        self._gripper = {int(k): str(v) for k, v in gripper_bodies.items()}
        self._pads = tuple(int(b) for b in pad_bodies)
        if len(self._pads) != 2:
            raise ValueError(f"pad_bodies: expected two body indices, got {pad_bodies!r}")
        self._grasp_body = int(grasp_body)
        self._X_BG = X_BG
        self._geometry = dict(geometry_bodies)
        self._table_z = float(table_z)
        self._contacts = self.DeclareAbstractInputPort(
            "contact_results", AbstractValue.Make(ContactResults()))
        self._poses = self.DeclareAbstractInputPort(
            "body_poses", AbstractValue.Make([RigidTransform()]))
        self._status = self.DeclareVectorInputPort("control_status", 3)
        self._state = self.DeclareAbstractState(AbstractValue.Make(JudgeHistory()))
        self.DeclarePeriodicUnrestrictedUpdateEvent(config.period_s, 0.0, self._Update)
        self.DeclareAbstractOutputPort(
            "judgement", lambda: AbstractValue.Make(GraspJudgement()), self._CalcJudgement)

    # -- queries -----------------------------------------------------------------------

    def get_history(self, context) -> JudgeHistory:
        return context.get_abstract_state(self._state).get_value()

    # -- what the inputs say -------------------------------------------------------------

    def _pairs(self, context) -> set:
        return body_contacts(self._contacts.Eval(context), self._geometry)

    def _holding(self, pairs) -> list[int]:
        """Scene indices of the objects that touch both pads."""
        return [i for i, b in enumerate(self._objects)
                if len(touching(pairs, b, self._pads)) == 2]

    def _lowest(self, context, i: int) -> float:
        X = self._poses.Eval(context)[self._objects[i]]
        P = self._points[i] @ X.rotation().matrix().T + X.translation()
        return float(P[:, 2].min()) - self._table_z

    def _xy(self, context) -> np.ndarray:
        poses = self._poses.Eval(context)
        return np.array([poses[b].translation()[:2] for b in self._objects]).reshape(-1, 2)

    def _nearest_to_grasp_axis(self, context) -> int | None:
        if not self._objects:
            return None
        poses = self._poses.Eval(context)
        axis = (poses[self._grasp_body] @ self._X_BG).translation()[:2]
        gaps = []
        for b, P in zip(self._objects, self._points):
            X = poses[b]
            xy = (P @ X.rotation().matrix().T + X.translation())[:, :2]
            gaps.append(float(np.min(np.linalg.norm(xy - axis, axis=1))))
        return int(np.argmin(gaps))

    # -- the update ----------------------------------------------------------------------

    def _Update(self, context, state):
        s = self.get_history(context)
        if s.verdict is not None:
            return
        t = context.get_time()
        phase = motion_phase_name(self._status.Eval(context)[2])
        new = s
        if phase != s.phase:
            new = replace(new, phase=phase, phase_start_s=s.phase_start_s + ((phase, t),))
            if phase == "descend":
                new = replace(new, descend_xy=tuple(map(tuple, self._xy(context))),
                              target=self._nearest_to_grasp_axis(context))
            if phase == "hold" and s.held is not None:
                pairs = self._pairs(context)
                new = replace(new, lift_end=(s.held in self._holding(pairs),
                                             self._lowest(context, s.held)))
        if phase == "done":
            new = replace(new, verdict=self._verdict(context, new))
        elif phase in ("descend", "close", "lift", "hold"):
            new = self._sample(context, new, phase, t)
        if new is not s:
            state.get_mutable_abstract_state(int(self._state)).set_value(new)

    def _sample(self, context, s: JudgeHistory, phase: str, t: float) -> JudgeHistory:
        """What the contacts at time t add to the history."""
        pairs = None
        if phase == "descend" and s.collision is None:
            pairs = self._pairs(context)
            hits = [(i, touching(pairs, b, self._gripper)) for i, b in enumerate(self._objects)]
            hits = [(i, hit) for i, hit in hits if hit]
            if hits:
                i, hit = hits[0]
                names = tuple(sorted({self._gripper[g] for _, h in hits for g in h}))
                s = replace(s, collision=(t, self._gripper[min(hit)], i, names))
        if phase == "close" and s.push_m is None and s.target is not None:
            pairs = self._pairs(context) if pairs is None else pairs
            if touching(pairs, self._objects[s.target], self._pads):
                s = replace(s, push_m=self._moved(context, s, s.target),
                            pads_touched_target_s=t)
        if phase == "lift" and not s.closed:  # the closing has just ended
            pairs = self._pairs(context) if pairs is None else pairs
            held = self._holding(pairs)
            if s.target in held:
                held = [s.target]
            s = replace(s, closed=True, held=held[0] if held else None)
            if s.push_m is None and s.target is not None:
                s = replace(s, push_m=self._moved(context, s, s.target))
        elif phase in ("lift", "hold") and s.held is not None and s.lost is None:
            pairs = self._pairs(context) if pairs is None else pairs
            if s.held not in self._holding(pairs):
                s = replace(s, lost=(t, phase))
        return s

    def _moved(self, context, s: JudgeHistory, i: int) -> float | None:
        if s.descend_xy is None:
            return None
        return float(np.linalg.norm(self._xy(context)[i] - np.asarray(s.descend_xy[i])))

    # -- the verdict ---------------------------------------------------------------------

    def _verdict(self, context, s: JudgeHistory) -> GraspJudgement:
        """The verdict when the motion is done, from the history and the contacts now."""
        times = {p: round(float(t), 4) for p, t in s.phase_start_s}
        details = {
            "phase_start_s": times,
            "target_object_id": self._ids[s.target] if s.target is not None else None,
            "target_push_m": s.push_m,
            "pads_touched_target_s": s.pads_touched_target_s,
            "collision": (None if s.collision is None else {
                "time_s": round(float(s.collision[0]), 4), "gripper_body": s.collision[1],
                "object_id": self._ids[s.collision[2]], "gripper_bodies": list(s.collision[3])}),
            "held_object_id": self._ids[s.held] if s.held is not None else None,
            "left_pads": (None if s.lost is None else
                          {"time_s": round(float(s.lost[0]), 4), "phase": s.lost[1]}),
            "after_lift": (None if s.lift_end is None else
                           {"both_pads": bool(s.lift_end[0]), "lowest_m": s.lift_end[1]}),
        }
        closed = s.closed or "lift" in times
        if not closed:
            return GraspJudgement(
                decided=True, attempted=False, failure="missed",
                reason="missed: the policy ended without closing the gripper", details=details)
        pairs = self._pairs(context)
        held_now = self._holding(pairs)
        lifted = [i for i in held_now if self._lowest(context, i) >= self._c.min_lift_m]
        if s.held in lifted:
            lifted = [s.held]
        subject = lifted[0] if lifted else (s.held if s.held is not None else s.target)
        lowest = self._lowest(context, subject) if subject is not None else None
        out = dict(decided=True, attempted=True, held_after_close=s.held is not None,
                   object_lowest_point_m=lowest, details=details)
        if lifted:
            return GraspJudgement(success=True, failure="", reason=None,
                                  grasped_object_id=self._ids[lifted[0]], **out)
        name = self._ids[subject] if subject is not None else "no object"
        if s.held is None:
            if s.push_m is not None and s.push_m > self._c.max_push_m:
                return GraspJudgement(failure="pushed-away", reason=(
                    f"pushed-away: {name} moved {100 * s.push_m:.1f} cm before the closing "
                    f"pads touched it, and nothing was held"), **out)
            if s.collision is not None:
                t, body, i, _ = s.collision
                return GraspJudgement(failure="collision", reason=(
                    f"collision: the gripper's {body} touched {self._ids[i]} during the "
                    f"descent (t = {t:.2f} s), and nothing was held"), **out)
            return GraspJudgement(failure="missed", reason=(
                "missed: no object touched both pads when the closing ended"), **out)
        min_lift = self._c.min_lift_m
        lift_ok = (s.lift_end is not None and s.lift_end[0] and s.lift_end[1] >= min_lift
                   and (s.lost is None or s.lost[1] != "lift"))
        where = "lift" if not lift_ok else "hold"
        return GraspJudgement(failure=f"slipped-during-{where}", reason=(
            f"slipped-during-{where}: {name} was held by both pads after closing but not "
            f"after the {where} (lowest point {100 * lowest:.1f} cm above the table, "
            f"{100 * min_lift:.0f} cm needed)"), **out)

    def _CalcJudgement(self, context, output):
        s = self.get_history(context)
        if s.verdict is not None:
            output.set_value(s.verdict)
            return
        phase = motion_phase_name(self._status.Eval(context)[2])
        if phase == "done":
            output.set_value(self._verdict(context, s))
            return
        output.set_value(GraspJudgement(
            decided=False, attempted=s.closed, failure="timeout", held_after_close=s.held is not None,
            reason=f"timeout: the grasp motion was in its {phase!r} phase when the episode ended",
            details={"phase_start_s": {p: round(float(t), 4) for p, t in s.phase_start_s}}))


__all__ = ["GraspJudge", "GraspJudgement", "JudgeHistory", "MOTION_PHASES", "PAD_BODIES",
           "body_contacts", "geometry_bodies", "pad_contacts", "touching"]
