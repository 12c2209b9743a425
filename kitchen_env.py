"""A MuJoCo stand-in for the RAMa paper's NVIDIA Isaac kitchen (Zholus & Panov, Appendix A).

A wheeled base (Husky-like) carrying one UR5-like arm stands before a table in a kitchen. A small blue object
(a box for `bluebox`, a cone for `bluecone`) lies on the table and has to be pushed into a blue target zone.
- observation: 96x64 RGB (uint8, height x width x 3) from a camera looking at the robot before the table;
  `obs_type="state"` gives a float32 vector instead (joints, knuckle, object, target) for cheap studies;
- action: one value in [-1, 1] per active joint, read as that joint's acceleration (Appendix A). The paper
  enables 3 joints (pan, lift, elbow: `active_joints=3`); `active_joints=7` adds three wrist joints and the finger;
- reward: the decrease of the object-to-target distance in centimetres, so the return telescopes to
  (initial - final distance); the object starts 50 cm from the zone's centre, so 50 is the maximal return;
- 500 control steps at 20 Hz per episode (truncated), terminated early if the object falls off the table.
What differs from the paper: rasterised primitives instead of the ray-traced Isaac kitchen asset, and the
wheeled base is static (the paper's agent never drives it either).

    import gymnasium as gym, kitchen_env
    env = gym.make("Kitchen-BlueBox-v0")            # or "Kitchen-BlueCone-v0", KitchenEnv(obs_type="state")
    python kitchen_env.py --pictures docs/          # observation/render PNGs and a GIF of the scripted expert
"""
import os

os.environ.setdefault("MUJOCO_GL", "egl")  # offscreen rendering; must be set before mujoco is imported

import gymnasium
import mujoco
import numpy as np

# ----------------------------------------------------------------------------------------------------------
# Scene constants (metres, radians)
TABLE_Z = 0.72  # height of the table's top surface
GOAL_XY = np.array([0.62, 0.0])  # centre of the blue target zone
ZONE_HALF = np.array([0.06, 0.08])  # the zone is a 12 x 16 cm rectangle
START_DISTANCE = 0.50  # object-to-zone distance at reset: the maximal return is 50 (cm)
SHOULDER_XY = np.array([0.15, 0.0])  # the arm's pan axis, used to keep object starts within reach
# start="fixed": the paper's "initial object position", one spot START_DISTANCE from the zone, yaw 0: on the zone's left
# (+y) at 100° around it, where the spot behind it is within reach (the random draw's range is 91-113°)
FIXED_START_ANGLE = np.deg2rad(100.0)
JOINTS = ("pan", "lift", "elbow", "wrist1", "wrist2", "wrist3", "finger")
HOME = np.array([0.0, 0.0, 2.10, 1.0, 0.0, 0.0, 0.02])  # hand above the table, pointing down
MAX_ACC = np.array([3.0, 3.0, 3.0, 4.0, 4.0, 4.0, 0.2])  # joint acceleration at action 1 (rad/s^2; m/s^2)
MAX_VEL = np.array([0.8, 0.8, 0.8, 1.2, 1.2, 1.2, 0.05])  # commanded joint speed limits
SLACK = np.array([0.15, 0.15, 0.15, 0.15, 0.15, 0.15, 0.01])  # how far a target may lead the measured joint
CONTROL_DT, PHYSICS_DT = 0.05, 0.002  # 20 Hz control over 25 physics steps


def _look_at(pos, target):
    """MJCF `xyaxes` of a camera at `pos` looking at `target` with a level horizon."""
    forward = np.asarray(target, float) - pos
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return " ".join(f"{v:.4f}" for v in (*right, *up))


CONE_RADIUS, CONE_HEIGHT = 0.04, 0.09
FRICTION = 'friction=".4 .005 .0001" priority="1"'  # priority 1: the object's friction wins over the table's


def _cone_xml(slabs=4, n=24):
    """MuJoCo has no cone primitive: the visible cone is a convex mesh (MuJoCo takes the hull of the vertex
    list) without contacts, and stacked hidden cylinders (group 3), each as wide as the cone at its mid-height,
    carry the contacts so that the cone rests flat on its base. Returns the mesh asset and the geoms."""
    ring = [(CONE_RADIUS * np.cos(a), CONE_RADIUS * np.sin(a), 0.0) for a in np.linspace(0, 2 * np.pi, n, False)]
    vertices = " ".join(f"{v:.4f}" for p in [*ring, (0.0, 0.0, CONE_HEIGHT)] for v in p)
    mesh = f'<mesh name="cone" vertex="{vertices}"/>'
    geoms = '<geom type="mesh" mesh="cone" material="object" contype="0" conaffinity="0" mass="0"/>'
    half = 0.8 * CONE_HEIGHT / slabs / 2  # the slabs cover the lower 80 %; the thin tip needs no contacts
    for i in range(slabs):
        z = (2 * i + 1) * half
        radius = CONE_RADIUS * (1 - z / CONE_HEIGHT)
        geoms += (f'<geom type="cylinder" size="{radius:.4f} {half:.4f}" pos="0 0 {z:.4f}" group="3" '
                  f'density="1000" {FRICTION}/>')
    return mesh, geoms


# (mesh asset, geoms) per task. The object body's origin is the centre of its base, so both start at TABLE_Z.
# The object's friction is low (0.4): with MuJoCo's default of 1 the pushed cone tilts and may tip over.
OBJECTS = {
    "bluebox": ("", f'<geom type="box" size=".03 .03 .03" pos="0 0 .03" material="object" mass=".2" {FRICTION}/>'),
    "bluecone": _cone_xml(),
}


def _kitchen_xml(task):
    """The whole scene as MJCF built from primitives. Collision masks: the world and the object have
    contype 1, the robot contype 2 with conaffinity 1, so the robot touches table and object but never
    itself (its static base would otherwise jam the shoulder). Furniture is visual only (class decor)."""
    cabinets = "".join(  # a row of cabinet doors with handles under the back counter
        f'<geom class="decor" type="box" size=".005 .27 .36" pos="-1.19 {y:.2f} .46" material="door"/>'
        f'<geom class="decor" type="box" size=".015 .06 .01" pos="-1.17 {y:.2f} .72" material="steel"/>'
        for y in np.arange(-1.5, 1.6, 0.6))
    camera = np.array([1.5, -0.6, 1.5])
    return f"""
<mujoco model="kitchen">
  <compiler angle="radian" autolimits="true"/>
  <!-- multiccd: several contacts between convex shapes; a cylinder on the table otherwise gets one, and the
       cone sinks into the table and creeps -->
  <option timestep="{PHYSICS_DT}" integrator="implicitfast"><flag multiccd="enable"/></option>
  <statistic extent="4" center="0.3 0 0.8"/>
  <visual>
    <global offwidth="1280" offheight="960"/>
    <map znear="0.005" zfar="25"/>  <!-- fractions of the extent: 2 cm near plane for a room-sized scene -->
    <quality shadowsize="2048"/>
    <headlight ambient=".35 .35 .35" diffuse=".4 .4 .4" specular=".1 .1 .1"/>
  </visual>
  <default>
    <geom contype="1" conaffinity="1"/>
    <default class="decor"><geom contype="0" conaffinity="0"/></default>
    <default class="robot">
      <geom contype="2" conaffinity="1" material="arm"/>
      <joint damping="20" armature="0.05"/>
      <position kp="300" forcerange="-150 150"/>
    </default>
  </default>
  <asset>
    <texture name="tiles" type="2d" builtin="checker" rgb1=".63 .55 .45" rgb2=".55 .47 .38" width="64" height="64"/>
    <material name="floor" texture="tiles" texrepeat="10 10"/>
    <material name="wall" rgba=".87 .85 .79 1"/>
    <material name="door" rgba=".93 .92 .88 1"/>
    <material name="counter" rgba=".22 .22 .24 1"/>
    <material name="wood" rgba=".58 .40 .24 1"/>
    <material name="steel" rgba=".70 .71 .72 1" specular=".6" shininess=".6"/>
    <material name="yellow" rgba=".95 .72 .08 1"/>
    <material name="black" rgba=".07 .07 .07 1"/>
    <material name="arm" rgba=".80 .80 .78 1" specular=".3"/>
    <material name="joint" rgba=".25 .25 .27 1"/>
    <material name="object" rgba=".05 .18 .95 1"/>
    <material name="zone" rgba=".30 .55 1 1"/>
    {OBJECTS[task][0]}
  </asset>
  <worldbody>
    <light name="ceiling" pos="0.3 0 2.6" dir="0 0 -1" diffuse=".55 .55 .55" castshadow="true"/>
    <light name="window" directional="true" pos="0 0 3" dir="-.4 .3 -1" diffuse=".25 .25 .25" castshadow="true"/>
    <camera name="front" pos="{' '.join(map(str, camera))}" xyaxes="{_look_at(camera, [0.4, 0.0, 0.93])}" fovy="45"/>
    <geom name="floor" type="box" size="3 3 .01" pos="0 0 -.01" material="floor"/>
    <!-- kitchen: walls, a counter with cabinets, a stove, a sink, upper cabinets and a fridge -->
    <geom class="decor" type="box" size=".05 3 1.4" pos="-1.85 0 1.4" material="wall"/>
    <geom class="decor" type="box" size="3 .05 1.4" pos="0 2.4 1.4" material="wall"/>
    <geom class="decor" type="box" size="3 .05 1.4" pos="0 -2.4 1.4" material="wall"/>
    <geom class="decor" type="box" size=".32 1.8 .44" pos="-1.5 0 .44" material="door"/>
    <geom class="decor" type="box" size=".34 1.82 .025" pos="-1.5 0 .905" material="counter"/>
    {cabinets}
    <geom class="decor" type="box" size=".25 .3 .005" pos="-1.5 -.9 .935" material="black"/>
    <geom class="decor" type="box" size=".2 .25 .01" pos="-1.5 .6 .925" material="steel"/>
    <geom class="decor" type="box" size=".18 1.8 .35" pos="-1.62 0 1.75" material="door"/>
    <geom class="decor" type="box" size=".35 .4 .95" pos="-1.45 2.0 .95" material="steel"/>
    <geom class="decor" type="box" size="1.2 .3 .45" pos=".6 2.05 .45" material="door"/>
    <geom class="decor" type="box" size="1.22 .32 .025" pos=".6 2.05 .925" material="counter"/>
    <!-- the table: its top collides, the legs are decor -->
    <geom name="table" type="box" size=".40 .70 .02" pos=".72 0 {TABLE_Z - 0.02}" material="wood"/>
    <geom class="decor" type="box" size=".03 .03 .35" pos=".36 .64 .35" material="wood"/>
    <geom class="decor" type="box" size=".03 .03 .35" pos=".36 -.64 .35" material="wood"/>
    <geom class="decor" type="box" size=".03 .03 .35" pos="1.08 .64 .35" material="wood"/>
    <geom class="decor" type="box" size=".03 .03 .35" pos="1.08 -.64 .35" material="wood"/>
    <geom name="zone" type="box" size="{ZONE_HALF[0]} {ZONE_HALF[1]} .0015" contype="0" conaffinity="0"
          pos="{GOAL_XY[0]} {GOAL_XY[1]} {TABLE_Z + 0.0015}" material="zone"/>
    <!-- the Husky-like base (static) with a pedestal for the arm -->
    <body name="husky" childclass="robot">
      <geom type="box" size=".40 .27 .10" pos="-.22 0 .25" material="yellow"/>
      <geom type="box" size=".2 .2 .012" pos="-.05 0 .36" material="joint"/>
      <geom type="box" size=".03 .30 .04" pos=".2 0 .2" material="black"/>
      <geom type="box" size=".03 .30 .04" pos="-.64 0 .2" material="black"/>
      <geom type="cylinder" size=".165 .05" pos=".04 .33 .165" zaxis="0 1 0" material="black"/>
      <geom type="cylinder" size=".165 .05" pos=".04 -.33 .165" zaxis="0 1 0" material="black"/>
      <geom type="cylinder" size=".165 .05" pos="-.48 .33 .165" zaxis="0 1 0" material="black"/>
      <geom type="cylinder" size=".165 .05" pos="-.48 -.33 .165" zaxis="0 1 0" material="black"/>
      <geom type="box" size=".09 .09 .15" pos="{SHOULDER_XY[0]} 0 .52" material="steel"/>
      <geom type="cylinder" size=".065 .02" pos="{SHOULDER_XY[0]} 0 .69" material="joint"/>
      <!-- the UR5-like arm; gravity compensation lets moderate servo gains track without sagging -->
      <body name="shoulder" pos="{SHOULDER_XY[0]} 0 .71" gravcomp="1">
        <joint name="pan" axis="0 0 1" range="-1.7 1.7"/>
        <geom type="cylinder" size=".06 .045" pos="0 0 .045" material="joint"/>
        <geom type="cylinder" size=".06 .065" pos="0 0 .09" zaxis="0 1 0" material="joint"/>
        <body name="upper_arm" pos="0 0 .09" gravcomp="1">
          <joint name="lift" axis="0 1 0" range="-0.5 1.6"/>
          <geom type="capsule" fromto="0 0 0 0 0 .425" size=".045"/>
          <geom type="cylinder" size=".05 .055" pos="0 0 .425" zaxis="0 1 0" material="joint"/>
          <body name="forearm" pos="0 0 .425" gravcomp="1">
            <joint name="elbow" axis="0 1 0" range="-0.3 2.7"/>
            <geom type="capsule" fromto="0 0 0 0 0 .39" size=".035"/>
            <body name="wrist1" pos="0 0 .39" gravcomp="1">
              <joint name="wrist1" axis="0 1 0" range="-3 3"/>
              <geom type="cylinder" size=".04 .045" zaxis="0 1 0" material="joint"/>
              <geom type="capsule" fromto="0 0 0 0 0 .05" size=".033"/>
              <body name="wrist2" pos="0 0 .06" gravcomp="1">
                <joint name="wrist2" axis="0 0 1" range="-3 3"/>
                <geom type="cylinder" size=".04 .025" pos="0 0 .01" material="joint"/>
                <body name="wrist3" pos="0 0 .045" gravcomp="1">
                  <joint name="wrist3" axis="1 0 0" range="-3 3"/>
                  <geom type="cylinder" size=".035 .03" zaxis="1 0 0" material="joint"/>
                  <geom type="box" size=".055 .03 .015" pos="0 0 .045" material="black"/>
                  <geom type="box" size=".008 .022 .03" pos="-.045 0 .09" material="arm"/>
                  <body name="finger" pos=".045 0 .09" gravcomp="1">
                    <joint name="finger" type="slide" axis="-1 0 0" range="0 .035"/>
                    <geom type="box" size=".008 .022 .03" material="arm"/>
                  </body>
                  <!-- the gripper's knuckle: the point the scripted expert pushes with -->
                  <site name="knuckle" pos="0 0 .1" size=".012" group="4"/>
                </body>
              </body>
            </body>
          </body>
        </body>
      </body>
    </body>
    <body name="object" pos="{GOAL_XY[0]} {GOAL_XY[1] - START_DISTANCE} {TABLE_Z}">
      <freejoint name="object"/>
      {OBJECTS[task][1]}
    </body>
  </worldbody>
  <actuator>
    {''.join(f'<position class="robot" name="{j}" joint="{j}"/>' for j in JOINTS[:-1])}
    <position class="robot" name="finger" joint="finger" kp="200" forcerange="-20 20"/>
  </actuator>
</mujoco>"""


# ----------------------------------------------------------------------------------------------------------
# The environment
class KitchenEnv(gymnasium.Env):
    """Push a blue box or cone into the blue zone with a Husky-like robot's arm (RAMa, Appendix A)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": int(round(1 / CONTROL_DT))}

    def __init__(self, task="bluebox", active_joints=3, obs_type="pixels", width=96, height=64, shadows=False,
                 max_steps=500, render_mode="rgb_array", start="fixed"):
        assert task in OBJECTS and active_joints in (3, 7) and obs_type in ("pixels", "state")
        assert start in ("fixed", "random"), f"start must be 'fixed' or 'random', not {start!r}"
        self.task, self.active_joints, self.obs_type, self.start = task, active_joints, obs_type, start
        self.width, self.height, self.shadows, self.max_steps = width, height, shadows, max_steps
        self.render_mode = render_mode
        self.model = mujoco.MjModel.from_xml_string(_kitchen_xml(task))
        self.data = mujoco.MjData(self.model)
        self._qadr = np.array([self.model.joint(j).qposadr[0] for j in JOINTS])
        self._dadr = np.array([self.model.joint(j).dofadr[0] for j in JOINTS])
        self._limits = self.model.jnt_range[[self.model.joint(j).id for j in JOINTS]].T  # (2, 7)
        self._obj = self.model.joint("object").qposadr[0]
        self._knuckle = self.model.site("knuckle").id
        self._renderers = {}  # (width, height) -> mujoco.Renderer, created on first use
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (active_joints,), np.float32)
        if obs_type == "pixels":
            self.observation_space = gymnasium.spaces.Box(0, 255, (height, width, 3), np.uint8)
        else:  # joint angles (7), joint velocities (7), knuckle (3), object (3), target (3)
            self.observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (23,), np.float32)

    # -- geometry the reward, the expert and the tests read
    def object_pos(self):
        return self.data.qpos[self._obj:self._obj + 3].copy()

    def knuckle_pos(self):
        return self.data.site_xpos[self._knuckle].copy()

    def distance_cm(self):
        """Object-to-zone-centre distance on the table plane, in centimetres (the reward's unit)."""
        return 100.0 * float(np.linalg.norm(self.object_pos()[:2] - GOAL_XY))

    def _info(self):
        inside = np.all(np.abs(self.object_pos()[:2] - GOAL_XY) <= ZONE_HALF)
        return {"distance": self._distance, "success": bool(inside)}

    # -- gymnasium API
    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[self._qadr] = HOME
        # The object starts exactly START_DISTANCE from the zone's centre. "fixed": always at FIXED_START_ANGLE with
        # yaw 0. "random": to the zone's left or right, on the table and within the arm's reach, and so is the spot
        # behind it where a pusher has to stand, with a random yaw.
        while True:
            angle = FIXED_START_ANGLE if self.start == "fixed" else self.np_random.uniform(-np.pi, np.pi)
            xy = GOAL_XY + START_DISTANCE * np.array([np.cos(angle), np.sin(angle)])
            behind = xy + 0.1 * (xy - GOAL_XY) / START_DISTANCE
            reach, reach_behind = np.linalg.norm(xy - SHOULDER_XY), np.linalg.norm(behind - SHOULDER_XY)
            if 0.38 <= reach <= 0.72 and reach_behind <= 0.76 and xy[0] >= 0.42 and abs(xy[1]) <= 0.5:
                break
        yaw = 0.0 if self.start == "fixed" else self.np_random.uniform(-np.pi, np.pi)
        self.data.qpos[self._obj:self._obj + 7] = [*xy, TABLE_Z, np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]
        self._target = HOME.copy()  # position-servo targets, integrated from the commanded velocities
        self._velocity = np.zeros(len(JOINTS))  # commanded joint velocities, integrated from the actions
        self.data.ctrl[:] = self._target
        mujoco.mj_forward(self.model, self.data)
        self._steps, self._distance = 0, self.distance_cm()
        return self.observe(), self._info()

    def step(self, action):
        reward, terminated, truncated, info = self.step_physics(action)
        return self.observe(), reward, terminated, truncated, info

    def step_physics(self, action):
        """One control step without the observation (reward, terminated, truncated, info): an action repeat observes
        only after its last step (rama_dreamer.ActionRepeat)."""
        n = self.active_joints
        acceleration = np.zeros(len(JOINTS))
        acceleration[:n] = np.clip(action, -1.0, 1.0) * MAX_ACC[:n]  # Appendix A: actions are accelerations
        velocity = np.clip(self._velocity + acceleration * CONTROL_DT, -MAX_VEL, MAX_VEL)
        target = np.clip(self._target + velocity * CONTROL_DT, *self._limits)
        # A target may lead the measured angle by at most SLACK: an arm blocked by the table or the object
        # then does not wind up and jump when released.
        q = self.data.qpos[self._qadr]
        target = np.clip(target, q - SLACK, q + SLACK)
        target[n:] = HOME[n:]  # inactive joints hold their home pose
        self._velocity = (target - self._target) / CONTROL_DT  # the velocity actually realised after clipping
        self._target = target
        self.data.ctrl[:] = target
        mujoco.mj_step(self.model, self.data, nstep=int(round(CONTROL_DT / PHYSICS_DT)))

        distance = self.distance_cm()
        reward = self._distance - distance  # telescopes: the return is initial - final distance
        self._distance, self._steps = distance, self._steps + 1
        terminated = bool(self.object_pos()[2] < TABLE_Z - 0.1)  # fell off the table
        truncated = self._steps >= self.max_steps
        return float(reward), terminated, truncated, self._info()

    def observe(self):
        if self.obs_type == "pixels":
            return self.render_frame(self.width, self.height)
        d = self.data
        state = [d.qpos[self._qadr], d.qvel[self._dadr], self.knuckle_pos(), self.object_pos(), [*GOAL_XY, TABLE_Z]]
        return np.concatenate(state).astype(np.float32)

    def render(self):
        return self.render_frame(self.width, self.height)

    def render_frame(self, width, height):
        """RGB frame (height, width, 3) uint8 from the front camera, at any size up to 1280x960."""
        if (width, height) not in self._renderers:
            # Multisampling triples the CPU render time of a 96x64 observation for little gain at that size,
            # so only larger frames (pictures, videos) get it. It is read when a renderer is created.
            self.model.vis.quality.offsamples = 0 if (width, height) == (self.width, self.height) else 4
            renderer = mujoco.Renderer(self.model, height, width)
            renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = self.shadows  # ~20x render time on CPU
            self._renderers[width, height] = renderer
        renderer = self._renderers[width, height]
        renderer.update_scene(self.data, camera="front")
        return renderer.render()

    def close(self):
        # Free the GL contexts now: left to the garbage collector at exit, EGL prints errors.
        for renderer in self._renderers.values():
            renderer.close()
        self._renderers.clear()


# ----------------------------------------------------------------------------------------------------------
# Scripted expert
def scripted_action(env):
    """Push the object into the zone with the gripper's knuckle: travel above the spot behind the object (as seen
    from the target), descend, then push along the object-to-target line. A Cartesian velocity for the knuckle
    is turned into joint velocities through the Jacobian of pan, lift and elbow, then into accelerations."""
    env = env.unwrapped
    knuckle, obj = env.knuckle_pos(), env.object_pos()
    to_goal = GOAL_XY - obj[:2]
    remaining = np.linalg.norm(to_goal)
    direction = to_goal / max(remaining, 1e-6)
    offset = knuckle[:2] - obj[:2]
    along = offset @ direction  # < 0: the knuckle is behind the object
    across = offset @ np.array([-direction[1], direction[0]])
    low, high = TABLE_Z + 0.03, TABLE_Z + 0.14
    if remaining < 0.01:  # arrived: keep still
        goal = knuckle
    elif along < -0.02 and abs(across) < 0.025 and knuckle[2] < low + 0.03:
        # Pushing: chase a point a little inside the object along the line, which keeps the contact centred;
        # the lead shrinks near the target so that the object is not overshot.
        goal = np.array([*(obj[:2] - direction * (0.06 - min(0.035, remaining))), low])
    else:
        # Repositioning: travel above the object's height to the spot behind it, descend once there.
        behind = obj[:2] - direction * 0.09
        arrived = np.linalg.norm(knuckle[:2] - behind) < 0.02
        goal = np.array([*behind, low if arrived else high])
        near_object = np.linalg.norm(offset) < 0.12
        if near_object and knuckle[2] < high - 0.04 and not arrived:  # rise first, not to sweep the object along
            goal[:2] = knuckle[:2]
    velocity = np.clip(4.0 * (goal - knuckle), -0.25, 0.25)  # desired knuckle velocity, m/s

    jacobian = np.zeros((3, env.model.nv))
    mujoco.mj_jacSite(env.model, env.data, jacobian, None, env._knuckle)
    jac = jacobian[:, env._dadr[:3]]  # (3, 3): pan, lift, elbow
    joint_velocity = jac.T @ np.linalg.solve(jac @ jac.T + 1e-4 * np.eye(3), velocity)  # damped least squares
    # The Cartesian controller stalls at joint limits and with the hand beside or under the table's edge (where
    # random actions may leave it): there the arm goes home in joint space, first leaning back if the hand is low.
    q, (lo, hi) = env.data.qpos[env._qadr], env._limits
    home = HOME.copy()
    if knuckle[2] < TABLE_Z + 0.05:
        home[1] = lo[1] + 0.1
    desired = np.clip(2.0 * (home - q), -MAX_VEL, MAX_VEL)  # wrist and finger always hold home
    lost = knuckle[0] < 0.34 or knuckle[2] < TABLE_Z - 0.01 or np.any(np.minimum(q - lo, hi - q)[:3] < 0.05)
    if not lost:
        desired[:3] = np.clip(joint_velocity, -MAX_VEL[:3], MAX_VEL[:3])
    action = (desired - env._velocity) / (MAX_ACC * CONTROL_DT)  # the acceleration that reaches it in one step
    return np.clip(action[:env.active_joints], -1.0, 1.0).astype(np.float32)


# ----------------------------------------------------------------------------------------------------------
# Registration: entry point by module path, so gymnasium.make works once kitchen_env is importable.
for _task in OBJECTS:
    _id = f"Kitchen-{'BlueBox' if _task == 'bluebox' else 'BlueCone'}-v0"
    if _id not in gymnasium.registry:  # the module may be imported twice (as __main__ and as kitchen_env)
        gymnasium.register(_id, entry_point="kitchen_env:KitchenEnv", kwargs={"task": _task})


if __name__ == "__main__":  # python kitchen_env.py --pictures docs/
    import argparse

    import imageio.v3 as iio

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pictures", default="docs", help="folder for the PNGs and the expert GIF")
    folder = parser.parse_args().pictures
    os.makedirs(folder, exist_ok=True)
    for task in OBJECTS:
        env = KitchenEnv(task=task)
        obs, _ = env.reset(seed=0)
        iio.imwrite(f"{folder}/kitchen_obs_{task}.png", obs.repeat(4, axis=0).repeat(4, axis=1))  # nearest 4x
        iio.imwrite(f"{folder}/kitchen_render_{task}.png", env.render_frame(480, 320))
        if task == "bluebox":  # the expert at 240x160, every 5th step (played 2.5x real time), until it arrives
            frames = []
            for step in range(env.max_steps):
                _, _, terminated, truncated, info = env.step(scripted_action(env))
                if step % 5 == 0:
                    frames.append(env.render_frame(240, 160))
                if terminated or truncated or info["distance"] < 1.0:  # the expert stops within 1 cm
                    break
            iio.imwrite(f"{folder}/kitchen_expert_{task}.gif", np.stack(frames), duration=100, loop=0)
            print(f"expert: {info['distance']:.2f} cm from the target after {step + 1} steps")
        env.close()
