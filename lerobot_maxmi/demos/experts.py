"""Scripted experts for ManiSkill tasks: one small state machine per task, reading privileged state.

Each expert computes a world-frame target pose for the TCP (`panda_hand_tcp`) and steers it there
through `pd_ee_delta_pose` (PickCube and StackCube also in `pd_ee_delta_pos`) with a proportional
law. Controller facts they rely on (ManiSkill 3.0.1, see /work/shared/notes/scripted_experts.md):

- A position action of 1.0 moves the target 0.1 m. One step achieves only ~40% of a command, so the
  law commands `gain` (1.5) times the error: ~60% of the error closes per step, without overshoot.
- Rotation actions are clipped to norm 1 and scaled by `rot_lower = -0.1`, which flips their sign;
  the experts negate them. Demos recorded here would replay mirrored on a ManiSkill that fixes this.
- The IK leaves the arm frozen for a step when a large step fails near the workspace edge, so speeds
  are capped (1.0 for transfers, lower for fine phases).
- Gripper: +1 opens, -1 closes.
"""

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import sapien
from scipy.spatial.transform import Rotation

POSITION_SCALE = 0.1  # metres per unit of position action
ROTATION_SCALE = 0.1  # radians per unit of rotation action
GRIPPER_OPEN = 1.0
GRIPPER_CLOSED = -1.0
CLOSE_STEPS = 4  # the gripper needs 3-4 steps to close on an object
RELEASE_STEPS = 3
DOWN = np.array([0.0, 0.0, -1.0])
# A command of at least LARGE_COMMAND (1 cm or 0.01 rad) that moves the TCP less than this is an IK stall.
LARGE_COMMAND = 0.1
STALL_DISTANCE = 0.001
STALL_ANGLE = 0.002
MIN_SCALE = 1 / 16


@dataclass(frozen=True)
class ExpertParams:
    """Knobs of the state machines; `randomized` draws them per episode for diverse demos."""

    gain: float = 1.5  # fraction of the remaining error commanded per step (x POSITION_SCALE)
    approach_height: float = 0.05  # hover height above the grasp point before descending
    lift_height: float = 0.06  # StackCube: carry height above the placing height
    grasp_offset: float = 0.0  # grasp point shift along the object's long axis (m)
    fine_speed: float = 0.3  # action cap in precise phases (descend, place, insert)

    @classmethod
    def randomized(cls, rng: np.random.Generator) -> "ExpertParams":
        return cls(
            gain=rng.uniform(1.2, 1.7),
            approach_height=rng.uniform(0.04, 0.08),
            lift_height=rng.uniform(0.04, 0.09),
            grasp_offset=rng.uniform(-0.006, 0.006),
            fine_speed=rng.uniform(0.25, 0.35),
        )


def as_sapien_pose(pose) -> sapien.Pose:
    """ManiSkill's batched Pose (num_envs == 1) as a plain sapien.Pose."""
    return pose.sp


def top_down_orientation(closing_axis: np.ndarray) -> np.ndarray:
    """TCP quaternion (wxyz) approaching straight down with the fingers closing along `closing_axis`.

    The TCP frame is [x = closing x approach, y = closing, z = approach] (Panda.build_grasp_pose).
    """
    closing = closing_axis - closing_axis @ DOWN * DOWN
    closing = closing / np.linalg.norm(closing)
    matrix = np.stack([np.cross(closing, DOWN), closing, DOWN], axis=1)
    return Rotation.from_matrix(matrix).as_quat(scalar_first=True)


def closest_face_axis(object_pose: sapien.Pose, reference: np.ndarray, away_from: np.ndarray | None = None):
    """The object's horizontal face normal (±x or ±y) closest to `reference`: the least wrist turn.

    With `away_from` (a direction to a neighbouring object), only the face axis more perpendicular to
    it qualifies, so the open fingers do not land on the neighbour.
    """
    rotation = object_pose.to_transformation_matrix()[:3, :3]
    axes = [rotation[:, 0], rotation[:, 1]]
    if away_from is not None:
        axes = [min(axes, key=lambda axis: abs(float(axis @ away_from)))]
    candidates = [sign * axis for axis in axes for sign in (1.0, -1.0)]
    return max(candidates, key=lambda axis: float(axis @ reference))


class PoseServo:
    """Turns a TCP target pose into a delta action with a capped proportional law.

    When the IK fails, ManiSkill's controller leaves the arm where it is and the same command would
    fail forever; a step without motion therefore halves the commands until the arm moves again.
    """

    def __init__(self, control_mode: str, gain: float):
        if control_mode not in ("pd_ee_delta_pose", "pd_ee_delta_pos"):
            raise ValueError(
                f"Scripted experts act in 'pd_ee_delta_pose' or 'pd_ee_delta_pos', got {control_mode!r}."
            )
        self.rotates = control_mode == "pd_ee_delta_pose"
        self.gain = gain
        self.reset()

    def reset(self) -> None:
        self.scale = 1.0
        self.last_tcp: sapien.Pose | None = None
        self.last_command_was_large = False

    def command(self, tcp: sapien.Pose, target: sapien.Pose, gripper: float, max_speed: float = 1.0):
        self._adapt_scale(tcp)
        arm = [_cap(self.gain * (target.p - tcp.p) / POSITION_SCALE, max_speed * self.scale)]
        if self.rotates:
            # Negated: ManiSkill 3.0.1 scales rotation actions by rot_lower (-0.1).
            arm.append(_cap(-self.gain * rotation_error(tcp, target) / ROTATION_SCALE, self.scale))
        self.last_command_was_large = max(np.linalg.norm(part) for part in arm) > LARGE_COMMAND
        return np.concatenate([*arm, [gripper]])

    def _adapt_scale(self, tcp: sapien.Pose) -> None:
        if self.last_tcp is not None and self.last_command_was_large:
            stalled = np.linalg.norm(tcp.p - self.last_tcp.p) < STALL_DISTANCE and (
                np.linalg.norm(rotation_error(tcp, self.last_tcp)) < STALL_ANGLE
            )
            self.scale = max(self.scale / 2, MIN_SCALE) if stalled else min(self.scale * 2, 1.0)
        self.last_tcp = tcp

    def reached(self, tcp: sapien.Pose, target: sapien.Pose, position_tol: float, rotation_tol: float):
        close = np.linalg.norm(target.p - tcp.p) < position_tol
        if not self.rotates:
            return close
        return close and np.linalg.norm(rotation_error(tcp, target)) < rotation_tol


def rotation_error(current: sapien.Pose, target: sapien.Pose) -> np.ndarray:
    """World-frame rotation vector taking `current` to `target` (the controller's rotation frame)."""
    to_rotation = lambda pose: Rotation.from_quat(pose.q, scalar_first=True)  # noqa: E731
    return (to_rotation(target) * to_rotation(current).inv()).as_rotvec()


def _cap(vector: np.ndarray, limit: float) -> np.ndarray:
    norm = np.linalg.norm(vector)
    return vector * (limit / norm) if norm > limit else vector


class ScriptedExpert:
    """A state machine: `self.phase` is the method that acts now; phases switch it when done.

    Every task starts with the same grasp: hover over `grasp_target`, descend, close; then the
    task's `after_grasp` phase takes over.
    """

    control_modes: tuple[str, ...] = ("pd_ee_delta_pose", "pd_ee_delta_pos")

    def __init__(self, control_mode: str = "pd_ee_delta_pose", params: ExpertParams | None = None):
        if control_mode not in self.control_modes:
            raise ValueError(
                f"{type(self).__name__} supports control modes {self.control_modes}, got {control_mode!r}."
            )
        self.params = params or ExpertParams()
        self.servo = PoseServo(control_mode, self.params.gain)
        self.phase: Callable = self.approach
        self.counter = 0  # steps spent in a timed phase (closing, releasing)

    def reset(self, env, params: ExpertParams | None = None) -> None:
        """Start a new episode on `env` (already reset), optionally with new parameters."""
        if params is not None:
            self.params = params
            self.servo.gain = params.gain
        self.servo.reset()
        self.plan(env.unwrapped)
        self.switch(self.approach)

    def act(self, env) -> np.ndarray:
        base = env.unwrapped
        return self.phase(base, as_sapien_pose(base.agent.tcp.pose)).astype(np.float32)

    def switch(self, phase: Callable) -> None:
        self.phase = phase
        self.counter = 0

    def plan(self, base) -> None:
        """Per-episode choices made from the initial scene (grasp orientation and point)."""
        raise NotImplementedError

    def grasp_target(self, base, height: float) -> sapien.Pose:
        """TCP pose `height` above the grasp pose of the object."""
        raise NotImplementedError

    def after_grasp(self, base, tcp: sapien.Pose) -> np.ndarray:
        raise NotImplementedError

    def approach(self, base, tcp):
        target = self.grasp_target(base, self.params.approach_height)
        if self.servo.reached(tcp, target, 0.02, 0.1):
            self.switch(self.descend)
        return self.servo.command(tcp, target, GRIPPER_OPEN)

    def descend(self, base, tcp):
        target = self.grasp_target(base, 0.0)
        if self.servo.reached(tcp, target, 0.005, 0.05):
            self.switch(self.close)
        return self.servo.command(tcp, target, GRIPPER_OPEN, self.params.fine_speed)

    def close(self, base, tcp):
        self.counter += 1
        if self.counter >= CLOSE_STEPS:
            self.switch(self.after_grasp)
        return self.servo.command(tcp, self.grasp_target(base, 0.0), GRIPPER_CLOSED)


class CubeGraspExpert(ScriptedExpert):
    """Top-down grasp of the task's cube, closing along the face axis nearest the current wrist yaw."""

    def cube(self, base):
        raise NotImplementedError

    def neighbour_direction(self, base, cube: sapien.Pose) -> np.ndarray | None:
        """Direction from the cube to an object the open fingers must not land on, if any."""
        return None

    def plan(self, base) -> None:
        tcp = as_sapien_pose(base.agent.tcp.pose)
        if self.servo.rotates:
            tcp_y = tcp.to_transformation_matrix()[:3, 1]
            cube = as_sapien_pose(self.cube(base).pose)
            closing = closest_face_axis(cube, tcp_y, self.neighbour_direction(base, cube))
            self.grasp_q = top_down_orientation(closing)
        else:
            self.grasp_q = tcp.q  # the 8 cm gripper takes a 4 cm cube at any yaw

    def grasp_target(self, base, height: float) -> sapien.Pose:
        cube = as_sapien_pose(self.cube(base).pose)
        return sapien.Pose(cube.p + np.array([0, 0, height + self.params.grasp_offset]), self.grasp_q)

    def carry(self, base, tcp: sapien.Pose, cube_target: np.ndarray) -> sapien.Pose:
        """TCP pose that brings the grasped cube's centre to `cube_target`, using the live grip offset."""
        cube = as_sapien_pose(self.cube(base).pose)
        return sapien.Pose(cube_target + (tcp.p - cube.p), self.grasp_q)


class PickCubeExpert(CubeGraspExpert):
    """Grasp the cube, carry its centre to the goal, hold still there (success needs a static robot)."""

    def cube(self, base):
        return base.cube

    def after_grasp(self, base, tcp):
        goal = as_sapien_pose(base.goal_site.pose).p
        return self.servo.command(tcp, self.carry(base, tcp, goal), GRIPPER_CLOSED)


class StackCubeExpert(CubeGraspExpert):
    """Grasp cube A, lift, move over B, lower until A rests 2 mm above B, release, retreat up."""

    def cube(self, base):
        return base.cubeA

    def neighbour_direction(self, base, cube: sapien.Pose) -> np.ndarray:
        return as_sapien_pose(base.cubeB.pose).p - cube.p

    def place_position(self, base, clearance: float) -> np.ndarray:
        cube_b = as_sapien_pose(base.cubeB.pose).p
        height = 2 * float(base.cube_half_size[2]) + clearance
        return cube_b + np.array([0, 0, height])

    def after_grasp(self, base, tcp):
        cube_a = as_sapien_pose(base.cubeA.pose).p
        lifted = np.array([*cube_a[:2], self.place_position(base, self.params.lift_height)[2]])
        target = self.carry(base, tcp, lifted)
        if self.servo.reached(tcp, target, 0.02, 0.1):
            self.switch(self.move_over)
        return self.servo.command(tcp, target, GRIPPER_CLOSED)

    def move_over(self, base, tcp):
        target = self.carry(base, tcp, self.place_position(base, 0.04))
        if self.servo.reached(tcp, target, 0.01, 0.1):
            self.switch(self.lower)
        return self.servo.command(tcp, target, GRIPPER_CLOSED)

    def lower(self, base, tcp):
        target = self.carry(base, tcp, self.place_position(base, 0.002))
        if self.servo.reached(tcp, target, 0.003, 0.1):
            self.switch(self.release)
        return self.servo.command(tcp, target, GRIPPER_CLOSED, self.params.fine_speed)

    def release(self, base, tcp):
        self.counter += 1
        if self.counter >= RELEASE_STEPS:
            self.retreat_target = sapien.Pose(tcp.p + np.array([0, 0, 0.05]), self.grasp_q)
            self.switch(self.retreat)
        return self.servo.command(tcp, tcp, GRIPPER_OPEN)

    def retreat(self, base, tcp):
        return self.servo.command(tcp, self.retreat_target, GRIPPER_OPEN, self.params.fine_speed)


class PegInsertionSideExpert(ScriptedExpert):
    """Grasp the peg toward its tail, lift, servo the *peg* pose in front of the hole, push it in.

    Servoing the peg (not the TCP) through the peg-to-TCP transform measured every step absorbs slip
    and tilt of the peg in the hand, which matters with a 3 mm clearance.
    """

    control_modes = ("pd_ee_delta_pose",)  # needs up to ~80 deg of yaw change
    insert_speed = 0.25  # ~1 cm per step
    standoff = 0.03  # gap between the peg head and the hole mouth before inserting
    align_tolerance = 0.003  # head and centre this close to the hole axis (y/z) before pushing
    push_tolerance = 0.004  # keep advancing only while y/z errors stay below this

    def plan(self, base) -> None:
        peg = as_sapien_pose(base.peg.pose)
        # Closing along -peg_y puts the TCP x axis (and the wrist camera) toward the head; +peg_y
        # would need a wrist turn past joint 7's limit at insertion.
        self.grasp_q = top_down_orientation(-peg.to_transformation_matrix()[:3, 1])
        self.half_length = float(base.peg_half_sizes[0, 0])
        # ManiSkill's motion-planning grasp point; nearer the centre, the wrist camera hits the box.
        self.tail_offset = max(0.05, self.half_length / 2 + 0.01) + self.params.grasp_offset

    def grasp_target(self, base, height: float) -> sapien.Pose:
        peg = as_sapien_pose(base.peg.pose)
        tail_ward = -peg.to_transformation_matrix()[:3, 0] * self.tail_offset
        return sapien.Pose(peg.p + tail_ward + np.array([0, 0, height]), self.grasp_q)

    def after_grasp(self, base, tcp):
        """Lift straight up before turning toward the hole."""
        if self.counter == 0:
            self.lift_target = sapien.Pose(tcp.p + np.array([0, 0, self.params.approach_height]), tcp.q)
        self.counter += 1
        if self.servo.reached(tcp, self.lift_target, 0.02, 0.1):
            self.switch(self.align)
        return self.servo.command(tcp, self.lift_target, GRIPPER_CLOSED)

    def peg_in_hole_frame(self, base) -> tuple[sapien.Pose, sapien.Pose, sapien.Pose]:
        """(goal pose, peg centre and peg head in the goal frame); the goal frame's x is the hole axis."""
        goal = as_sapien_pose(base.goal_pose)
        to_goal = goal.inv()
        return goal, to_goal * as_sapien_pose(base.peg.pose), to_goal * as_sapien_pose(base.peg_head_pose)

    def tcp_for_peg_at(self, base, tcp: sapien.Pose, peg_target: sapien.Pose) -> sapien.Pose:
        peg_to_tcp = as_sapien_pose(base.peg.pose).inv() * tcp
        return peg_target * peg_to_tcp

    def align(self, base, tcp):
        goal, centre, head = self.peg_in_hole_frame(base)
        peg_target = goal * sapien.Pose([-(self.half_length + self.standoff), 0, 0])
        off_axis = max(np.linalg.norm(centre.p[1:]), np.linalg.norm(head.p[1:]))
        target = self.tcp_for_peg_at(base, tcp, peg_target)
        if off_axis < self.align_tolerance and self.servo.reached(tcp, target, 0.01, 0.05):
            self.switch(self.insert)
        return self.servo.command(tcp, target, GRIPPER_CLOSED, 0.5)

    def insert(self, base, tcp):
        goal, centre, head = self.peg_in_hole_frame(base)
        off_axis = max(np.linalg.norm(centre.p[1:]), np.linalg.norm(head.p[1:]))
        advance = 0.03 if off_axis < self.push_tolerance else 0.0
        peg_target = goal * sapien.Pose([centre.p[0] + advance, 0, 0])
        target = self.tcp_for_peg_at(base, tcp, peg_target)
        return self.servo.command(tcp, target, GRIPPER_CLOSED, self.insert_speed)


EXPERTS: dict[str, type[ScriptedExpert]] = {
    "PickCube-v1": PickCubeExpert,
    "StackCube-v1": StackCubeExpert,
    "PegInsertionSide-v1": PegInsertionSideExpert,
}


def make_expert(task: str, control_mode: str = "pd_ee_delta_pose") -> ScriptedExpert:
    if task not in EXPERTS:
        raise ValueError(
            f"No scripted expert for {task!r}; experts exist for {', '.join(EXPERTS)}. For other tasks "
            "(e.g. TurnFaucet-v1, whose assets need a download), convert existing demonstrations with "
            "`lerobot-maxmi-convert --format=maniskill_h5 --path=<trajectory.h5> --repo_id=...`."
        )
    return EXPERTS[task](control_mode)
