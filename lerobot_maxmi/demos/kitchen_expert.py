"""A scripted Franka Kitchen expert that completes an ordered chain of subtasks.

It reads the simulator state (privileged, as a demo generator may) and acts through the env's own
action space: 9 joint velocities. Each step it solves inverse kinematics on a scratch copy of the
model for a Cartesian end-effector target (home orientation: gripper pointing into the kitchen,
+y, optionally rolled about it), then drives the joints there. Each subtask is a short list of
phases (approach, manipulate, back off); targets follow the moving handle, so doors are pulled along
their own arcs, burner knobs are grasped and turned by rolling the wrist, and the kettle is carried by
its handle. Between subtasks the arm passes a via point solved from the home posture, and settles
there, so errors in its redundant DOF do not pile up.

Diversity comes from a per-episode `rng`: approach offsets, speeds and via points are jittered, and
the recorder adds action noise.
"""

from collections.abc import Callable
from dataclasses import dataclass

import mujoco
import numpy as np

from lerobot_maxmi.envs.kitchen import task_completed

ARM = slice(0, 7)
FINGERS = slice(7, 9)
OPEN, CLOSED = 0.04, 0.0  # finger joint targets
STEP_SECONDS = 0.08  # frame_skip 40 x timestep 0.002: one env step
ACTION_SCALE = 2.0  # the env multiplies actions by 2 to get joint velocities (rad/s)
EE_SITE = "end_effector"


@dataclass
class Phase:
    """Move the end effector towards `target(data)` with the fingers at `fingers` until `done(data)`."""

    target: Callable[[mujoco.MjData], np.ndarray]
    fingers: float
    done: Callable[[mujoco.MjData], bool]
    max_steps: int
    roll: Callable[[mujoco.MjData], float] = lambda data: 0.0  # gripper roll about world +y (rad)
    # Solve the IK from the home posture, not the current one, and move there in joint space: resets
    # the arm's redundant DOF, which otherwise drifts over a chain into branches that hit the doors.
    from_home: bool = False


class JointVelocityIK:
    """End-effector position targets -> the env's joint-velocity actions (orientation held at home)."""

    def __init__(self, model: mujoco.MjModel, home_qpos: np.ndarray, max_speed: float = 0.6):
        self.model = model
        self.scratch = mujoco.MjData(model)
        self.site = model.site(EE_SITE).id
        self.max_speed = max_speed  # m/s of the Cartesian target
        self.kp_actuators = model.actuator_gainprm[ARM, 0].copy()
        self.joint_range = model.jnt_range[ARM].copy()
        self.home_rotation = self._site_rotation(home_qpos)
        self.home_qpos = home_qpos.copy()

    def _site_rotation(self, qpos: np.ndarray) -> np.ndarray:
        self.scratch.qpos[:] = qpos
        mujoco.mj_kinematics(self.model, self.scratch)
        return self.scratch.site_xmat[self.site].reshape(3, 3).copy()

    def action(self, data: mujoco.MjData, phase: Phase) -> np.ndarray:
        target, roll = phase.target(data), phase.roll(data)
        cos, sin = np.cos(roll), np.sin(roll)
        rotation = np.array([[cos, 0.0, sin], [0.0, 1.0, 0.0], [-sin, 0.0, cos]]) @ self.home_rotation
        if phase.from_home:
            q_target = self._solve(self.home_qpos, target, rotation, iterations=20)
        else:
            position = data.site_xpos[self.site]
            step = target - position
            max_step = self.max_speed * STEP_SECONDS * 2  # two steps ahead: the servo lags about one
            norm = np.linalg.norm(step)
            if norm > max_step:
                step *= max_step / norm
            q_target = self._solve(data.qpos, position + step, rotation)
        q = data.qpos[ARM]
        velocity = np.clip(10.0 * (q_target - q), -2.0, 2.0)
        # The action shifts a position servo's setpoint: offset it by gravity so the arm does not sag.
        gravity = data.qfrc_bias[ARM] / (self.kp_actuators * STEP_SECONDS)
        finger_velocity = np.full(2, 20.0 * (phase.fingers - data.qpos[FINGERS].mean()))
        return np.clip(np.concatenate([velocity + gravity, finger_velocity]) / ACTION_SCALE, -1.0, 1.0)

    def _solve(
        self, qpos: np.ndarray, target: np.ndarray, target_rotation: np.ndarray, iterations: int = 8
    ) -> np.ndarray:
        """Damped least squares from `qpos`, clamped to the joint limits."""
        scratch, model = self.scratch, self.model
        scratch.qpos[:] = qpos
        jac_position, jac_rotation = np.zeros((3, model.nv)), np.zeros((3, model.nv))
        for _ in range(iterations):
            mujoco.mj_kinematics(model, scratch)
            mujoco.mj_comPos(model, scratch)
            rotation = scratch.site_xmat[self.site].reshape(3, 3)
            error = np.concatenate(
                [
                    target - scratch.site_xpos[self.site],
                    0.5 * np.cross(rotation, target_rotation, axis=0).sum(axis=1),
                ]
            )
            if np.linalg.norm(error) < 1e-3:
                break
            mujoco.mj_jacSite(model, scratch, jac_position, jac_rotation, self.site)
            jacobian = np.vstack([jac_position[:, ARM], jac_rotation[:, ARM]])
            delta = jacobian.T @ np.linalg.solve(jacobian @ jacobian.T + 0.01 * np.eye(6), error)
            scratch.qpos[ARM] = np.clip(scratch.qpos[ARM] + delta, *self.joint_range.T)
        return scratch.qpos[ARM].copy()


class KitchenExpert:
    """Runs the phases of an ordered chain of subtasks; `act(data)` gives the next env action."""

    def __init__(self, model: mujoco.MjModel, home_qpos: np.ndarray):
        self.model = model
        self.ik = JointVelocityIK(model, home_qpos)
        self.scratch = mujoco.MjData(model)
        self.site = model.site(EE_SITE).id
        self.phases: list[Phase] = []
        self.phase_steps = 0

    def reset(self, tasks, rng: np.random.Generator) -> None:
        self.rng = rng
        self.ik.max_speed = rng.uniform(0.8, 1.0)
        self.pending = list(tasks)
        self.retries = dict.fromkeys(tasks, RETRIES)
        self.achieved: set[str] = set()
        self.task: str | None = None
        self.phases = []

    @property
    def done(self) -> bool:
        return not self.phases and self.task is None

    def act(self, data: mujoco.MjData) -> np.ndarray:
        while True:
            while self.phases and (self.phases[0].done(data) or self.phase_steps >= self.phases[0].max_steps):
                self.phases.pop(0)
                self.phase_steps = 0
            if self.phases:
                break
            if not self._plan_next(data):
                return np.zeros(9)
        self.phase_steps += 1
        phase = self.phases[0]
        return self.ik.action(data, phase)

    def _plan_next(self, data: mujoco.MjData) -> bool:
        """Plan the next subtask (retrying one that failed); False when none is left."""
        if self.task is not None and not self._achieved(data, self.task) and self.retries[self.task]:
            self.retries[self.task] -= 1
            self.pending.insert(0, self.task)
        # Skip subtasks that are already complete (e.g. a knob turned by a neighbouring push).
        self.pending = [task for task in self.pending if not self._achieved(data, task)]
        self.task = self.pending.pop(0) if self.pending else None
        if self.task is None:
            return False
        self.phases, self.phase_steps = self._plan(self.task, self.rng), 0
        return True

    def _achieved(self, data: mujoco.MjData, task: str) -> bool:
        """Complete now or at some earlier step (what a demo counts)."""
        return task in self.achieved or task_completed(data.qpos[:30], task)

    # Geometry helpers -------------------------------------------------------------------------------

    def ee(self, data: mujoco.MjData) -> np.ndarray:
        return data.site_xpos[self.site]

    def near(self, target: Callable, tolerance: float = 0.02) -> Callable[[mujoco.MjData], bool]:
        """Within `tolerance` of the target, or stalled close to it (a handle or panel in the way)."""

        def arrived(data):
            distance = np.linalg.norm(self.ee(data) - target(data))
            stalled = np.abs(data.qvel[ARM]).max() < STALL_SPEED
            return distance < tolerance or (distance < STALL_DISTANCE and stalled)

        return arrived

    def site_at(self, data: mujoco.MjData, site: str, joint: int, angle: float) -> np.ndarray:
        """Where `site` would be with qpos[joint] = angle: a point on the handle's arc."""
        self.scratch.qpos[:] = data.qpos
        self.scratch.qpos[joint] = angle
        mujoco.mj_kinematics(self.model, self.scratch)
        return self.scratch.site(site).xpos.copy()

    def fixed(self, point: np.ndarray) -> Callable:
        return lambda data: point

    def offset(self, site: str, delta) -> Callable:
        delta = np.asarray(delta, dtype=float)
        return lambda data: data.site(site).xpos + delta

    def anchored(self, site: str, *deltas) -> list[Callable]:
        """Fixed points at `deltas` from where `site` is when the first of them is asked for."""
        anchor = {}

        def point(delta):
            return lambda data: anchor.setdefault("p", data.site(site).xpos.copy()) + delta

        return [point(np.asarray(delta, dtype=float)) for delta in deltas]

    def lead(self, target: Callable, distance: float) -> Callable:
        """A point at most `distance` ahead of the end effector on its way to `target`: a slow move."""

        def carrot(data):
            step = target(data) - self.ee(data)
            return self.ee(data) + step * min(1.0, distance / max(np.linalg.norm(step), 1e-9))

        return carrot

    # Subtask plans ---------------------------------------------------------------------------------

    def _plan(self, task: str, rng: np.random.Generator) -> list[Phase]:
        def completed(data):
            if task_completed(data.qpos[:30], task):
                self.achieved.add(task)  # a door may swing back a little once released
            return task in self.achieved

        jitter = rng.uniform(-0.015, 0.015, size=3)
        plan = PLANS[task](self, completed, jitter, rng)
        # Back off towards the robot: the next approach then starts clear of handles and doors.
        back = rng.uniform(0.1, 0.16)
        retreat_target = {}

        def retreat(data):
            return retreat_target.setdefault("p", self.ee(data) - np.array([0.0, back, -0.02]))

        # Then pass a via point in front of the kitchen: straight paths from the open microwave to the
        # switches and knobs hit its door.
        via = self.fixed(VIA_POINT + rng.uniform(-0.04, 0.04, size=3))
        near_via = self.near(via, 0.05)

        def settled_at_via(data):  # the redundant DOF too: the end effector gets there first
            return near_via(data) and np.abs(data.qvel[ARM]).max() < STALL_SPEED

        return [
            *plan,
            Phase(retreat, OPEN, self.near(retreat, 0.03), 20),
            Phase(via, OPEN, settled_at_via, 25, from_home=True),
        ]


def _push(expert, completed, site, start, direction, distance, jitter, rng) -> list[Phase]:
    """Approach `site + start` from the front, then push along `direction` until the task completes."""
    start = np.asarray(start) + jitter
    front = start + np.array([0.0, -rng.uniform(0.08, 0.14), 0.0])
    push = start + distance * np.asarray(direction)
    return [
        Phase(expert.offset(site, front), CLOSED, expert.near(expert.offset(site, front), 0.03), 40),
        Phase(expert.offset(site, start), CLOSED, expert.near(expert.offset(site, start)), 30),
        Phase(expert.offset(site, push), CLOSED, completed, 60),
    ]


def _after(steps: int) -> Callable[[mujoco.MjData], bool]:
    """A phase end test that holds for `steps` steps (e.g. to let the fingers close)."""
    count = {"n": 0}

    def done(data):
        count["n"] += 1
        return count["n"] > steps

    return done


def _pull_door(expert, completed, site, joint, step, grasp_offset, jitter, rng) -> list[Phase]:
    """Grasp a vertical handle and pull it along the door's arc (`step` radians ahead each step)."""
    grasp = np.asarray(grasp_offset) + jitter * np.array([0.3, 0.3, 1.0])
    front = grasp + np.array([0.0, -rng.uniform(0.1, 0.14), 0.0])
    at_handle = expert.offset(site, grasp)

    def along_arc(data):
        return expert.site_at(data, site, joint, data.qpos[joint] + step) + grasp

    return [
        Phase(expert.offset(site, front), OPEN, expert.near(expert.offset(site, front), 0.03), 40),
        Phase(at_handle, OPEN, expert.near(at_handle, 0.012), 30),
        Phase(at_handle, CLOSED, _after(5), 6),
        Phase(along_arc, CLOSED, completed, 80),
        Phase(along_arc, OPEN, _after(4), 4),
    ]


STALL_SPEED = 0.1  # rad/s: below this on every arm joint, the arm is blocked
STALL_DISTANCE = 0.03  # m: a blocked approach this close to its target counts as arrived
RETRIES = 1  # a subtask whose plan ends incomplete is planned again (new jitter) this many times
VIA_POINT = np.array([-0.35, 0.35, 2.15])
FINGERTIP_REACH = 0.045  # closed fingertips reach this far beyond the end-effector site (+y)


def _turn_knob(expert, completed, site, joint, jitter, rng) -> list[Phase]:
    """Grasp a burner knob's grip bar and roll the wrist to turn it.

    The gripper points along the knob's axis (-y), so rolling about +y turns the knob: a negative
    knob angle is a positive roll. The bar (28 mm wide) fits between the open fingers.
    """
    # Fingertips just past the bar's centre, short of the knob's base behind it.
    grasp = np.array([0.0, -0.9 * FINGERTIP_REACH, 0.0]) + jitter * np.array([0.2, 0.1, 0.3])
    front = grasp + np.array([0.0, -rng.uniform(0.08, 0.12), 0.0])
    at_bar = expert.offset(site, grasp)
    lead = rng.uniform(0.35, 0.5)  # radians of roll ahead of the knob

    def twist(data):
        return -data.qpos[joint] + lead

    return [
        Phase(expert.offset(site, front), OPEN, expert.near(expert.offset(site, front), 0.03), 40),
        Phase(at_bar, OPEN, expert.near(at_bar, 0.012), 30),
        Phase(at_bar, CLOSED, _after(4), 5),
        Phase(at_bar, CLOSED, completed, 40, twist),
        Phase(at_bar, OPEN, _after(3), 3, twist),
    ]


def _carry_kettle(expert, jitter, rng) -> list[Phase]:
    """Grasp the kettle handle's left post, lift the kettle, carry it to the back burner, set it down.

    (Pushed, it yaws and stalls.) Held by one post it hangs a little tilted, so it is lifted well clear
    of the stove, and carried slowly so that it does not swing. It moves right as well as back: its
    spout would catch on the microwave. The wrist is rolled a little throughout: unrolled, joint 7
    reaches its limit before the back burner.
    """
    grasp = KETTLE_POST + jitter * np.array([0.2, 0.2, 1.0])
    front = grasp + np.array([0.0, -rng.uniform(0.08, 0.12), 0.0])
    at_front, at_post = expert.offset("kettle_site", front), expert.offset("kettle_site", grasp)
    lift = np.array([0.0, 0.0, rng.uniform(0.08, 0.1)])
    carry = np.array([rng.uniform(0.05, 0.07), rng.uniform(0.25, 0.29), 0.0])
    back = np.array([0.0, -0.08, 0.0])
    # Fixed from the grasp on: up, over the back burner, down, and straight back off the post.
    raised, over, down, clear = expert.anchored(
        "kettle_site", grasp + lift, grasp + lift + carry, grasp + carry, grasp + carry + back
    )
    roll_angle = rng.uniform(-0.35, -0.25)

    def roll(data):
        return roll_angle

    return [
        Phase(at_front, OPEN, expert.near(at_front, 0.03), 40, roll),
        Phase(at_post, OPEN, expert.near(at_post, 0.012), 30, roll),
        Phase(at_post, CLOSED, _after(5), 6, roll),
        Phase(expert.lead(raised, 0.02), CLOSED, expert.near(raised, 0.015), 20, roll),
        Phase(expert.lead(over, 0.03), CLOSED, expert.near(over, 0.02), 50, roll),
        Phase(expert.lead(down, 0.02), CLOSED, expert.near(down, 0.015), 25, roll),
        Phase(down, OPEN, _after(6), 6, roll),
        Phase(clear, OPEN, expert.near(clear, 0.02), 10, roll),
    ]


# The handle's left post (vertical, 23 mm radius) from kettle_site, atop the handle: the post ends up
# between the middles of the finger pads.
KETTLE_POST = np.array([-0.091, -0.02, -0.08])
PLANS = {
    "slide cabinet": lambda e, c, j, r: _push(e, c, "slide_site", [-0.07, 0, 0], [1, 0, 0], 0.3, j, r),
    "light switch": lambda e, c, j, r: _push(
        e, c, "light_site", [0.07, 0.0, 0], [-1, 0.3, 0], 0.25, j * 0.3, r
    ),
    "kettle": lambda e, c, j, r: _carry_kettle(e, j, r),
    "bottom burner": lambda e, c, j, r: _turn_knob(e, c, "knob2_site", 11, j, r),
    "top burner": lambda e, c, j, r: _turn_knob(e, c, "knob4_site", 15, j, r),
    "microwave": lambda e, c, j, r: _pull_door(e, c, "microhandle_site", 22, -0.3, [0, 0, 0], j, r),
    "hinge cabinet": lambda e, c, j, r: _pull_door(e, c, "hinge_site2", 21, 0.2, [0, 0, -0.05], j * 0.3, r),
}

# The open hinge-cabinet door swings in front of the slide cabinet's handle.
MUST_PRECEDE = {("slide cabinet", "hinge cabinet")}
