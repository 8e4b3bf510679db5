"""MuJoCo model of a WorldSpec: field, landmarks, lakes, and a quadcopter with a forward camera.

The quadcopter is a free rigid body (1 kg) moved only by a thrust force along its body z axis and three
body torques. A cascaded controller (`DroneController`, run at every physics step) turns the policy's
command (forward velocity, yaw rate) into those four inputs: velocity loop -> desired tilt and thrust,
altitude loop -> thrust, attitude loop -> roll/pitch torques, yaw-rate loop -> yaw torque. This stands in
for AirSim's flight controller in the paper ("velocity commands to the flight controller in its local
reference frame"). Contacts are disabled: the drone flies at a fixed altitude and landmarks are scenery;
there is no aerodynamic drag.

The forward camera sits on an ideal two-axis gimbal, as on camera drones: it follows the drone's position
and heading, but its roll stays level and its pitch fixed (27 deg down), so the far field stays in view
while the drone tilts to accelerate. Its exact pose is exposed either way.

Camera conventions. MuJoCo cameras look along their -z with +y up. Everything this module exposes uses the
computer-vision convention instead: camera x right, y down, z forward, and pixel (u, v) with the centre
of the top-left pixel at (0.5, 0.5), so K = [[f, 0, W/2], [0, f, H/2], [0, 0, 1]] with f = (W/2)/tan(HFOV/2).
"""

from __future__ import annotations

import math

import mujoco  # gsmn/__init__.py has set MUJOCO_GL=egl before this import
import numpy as np

from gsmn.config import CameraConfig, DroneConfig, RunConfig
from gsmn.world import shadows
from gsmn.world.assets import AssetModel, load_catalogue
from gsmn.world.spec import WorldSpec

GRAVITY = 9.81
HEADLIGHT = (0.35, 0.25)  # the headlight's ambient and diffuse grey (it follows the camera)
SUN = 0.75  # the sun's diffuse grey (its blue a little less: 0.72)
SUN_DIR = (0.35, 0.25, -1.0)  # the way the sun shines; it casts the shadows
FPV_CAMERA = "fpv"
TOPDOWN_CAMERA = "topdown"
# MuJoCo camera frame (x right, y up, looking along -z) -> computer-vision frame (x right, y down, z forward).
R_GL_CV = np.diag([1.0, -1.0, -1.0])

_BASE_XML = """
<mujoco model="gsmn_world">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{dt}" gravity="0 0 -{g}" integrator="RK4">
    <flag contact="disable"/>
  </option>
  <visual>
    <quality shadowsize="{shadow_size}" offsamples="{offsamples}"/>
    <global offwidth="{offwidth}" offheight="{offheight}"/>
    <headlight ambient="{head_ambient}" diffuse="{head_diffuse}" specular="0 0 0"/>
    <map znear="0.02" zfar="200"/>
  </visual>
  <asset>
    <texture name="sky" type="skybox" builtin="gradient" rgb1="0.55 0.72 0.92" rgb2="0.92 0.95 1.0"
             width="256" height="256"/>
    <texture name="grass" type="2d" builtin="checker" rgb1="0.36 0.58 0.25" rgb2="0.33 0.55 0.23"
             width="64" height="64"/>
    {field_texture}
    <material name="field" texture="{field_material_texture}" texrepeat="{field_repeat} {field_repeat}" specular="0"
              shininess="0" reflectance="0"/>
    <material name="outside" rgba="0.52 0.50 0.38 1" specular="0" reflectance="0"/>
    <material name="water" rgba="0.20 0.42 0.75 1" specular="0.3" shininess="0.6"/>
  </asset>
  <worldbody>
    <light name="sun" directional="true" pos="0 0 30" dir="{sun_dir}" diffuse="{sun} {sun} {sun_blue}"
           specular="0.1 0.1 0.1" castshadow="{shadows}"/>
    <geom name="outside" type="plane" size="{outside} {outside} 0.1" pos="{half} {half} -0.02"
          material="outside"/>
    <geom name="field" type="plane" size="{half} {half} 0.1" pos="{half} {half} 0" material="field"/>
    <camera name="{topdown}" mode="fixed" pos="{half} {half} 60" xyaxes="1 0 0 0 1 0"
            projection="orthographic" fovy="{topdown_extent}"/>
    <body name="drone" pos="0 0 {altitude}">
      <freejoint name="drone"/>
      <inertial pos="0 0 0" mass="{mass}" diaginertia="{ixx} {ixx} {izz}"/>
      <site name="imu" pos="0 0 0" size="0.01"/>
      <geom name="hull" type="box" size="0.09 0.06 0.03" rgba="0.15 0.15 0.17 1" mass="0"/>
      <geom name="nose" type="box" size="0.03 0.04 0.02" pos="0.1 0 0" rgba="0.9 0.3 0.1 1" mass="0"/>
      {arms}
    </body>
    <body name="gimbal" mocap="true" pos="0 0 {altitude}">
      <camera name="{fpv}" pos="{cam_forward} 0 0" xyaxes="0 -1 0 {sp} 0 {cp}" fovy="{fovy}"/>
    </body>
  </worldbody>
  <actuator>
    <motor name="thrust" site="imu" gear="0 0 1 0 0 0" ctrlrange="0 {max_thrust}"/>
    <motor name="roll" site="imu" gear="0 0 0 1 0 0" ctrlrange="-5 5"/>
    <motor name="pitch" site="imu" gear="0 0 0 0 1 0" ctrlrange="-5 5"/>
    <motor name="yaw" site="imu" gear="0 0 0 0 0 1" ctrlrange="-5 5"/>
  </actuator>
</mujoco>
"""


def _arms_xml(arm: float) -> str:
    parts = []
    for k in range(4):
        a = math.pi / 4 + k * math.pi / 2
        x, y = arm * math.cos(a), arm * math.sin(a)
        parts.append(f'<geom type="capsule" fromto="0 0 0 {x:.4f} {y:.4f} 0" size="0.012" '
                     f'rgba="0.2 0.2 0.22 1" mass="0"/>')
        parts.append(f'<geom type="cylinder" pos="{x:.4f} {y:.4f} 0.025" size="0.07 0.004" '
                     f'rgba="0.75 0.78 0.8 0.6" mass="0"/>')
    return "\n      ".join(parts)


def intrinsics(camera: CameraConfig) -> np.ndarray:
    """Pinhole intrinsics K (3, 3) of the forward camera, principal point at the image centre."""
    f = camera.focal
    return np.array([[f, 0.0, camera.width / 2], [0.0, f, camera.height / 2], [0.0, 0.0, 1.0]])


def build_spec(world: WorldSpec, config: RunConfig, catalogue: tuple[AssetModel, ...] | None = None
               ) -> mujoco.MjSpec:
    """An MjSpec of the world: base scene and drone from XML, then landmark meshes and lakes added. With baked
    shadows each landmark part's faces in another's shadow go into a darker geom of their own (the world compiled
    once as it is, for MuJoCo's ray casting, to find them)."""
    catalogue = catalogue or load_catalogue()
    shades = {}
    if config.camera.baked_shadows:
        model = _spec(world, config, catalogue, {}).compile()
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        blocked = shadows.ray_test(model, data, model.body("drone").id)
        shades = shadows.face_shades(world, catalogue, np.array(SUN_DIR), HEADLIGHT, SUN, blocked)
    return _spec(world, config, catalogue, shades)


def _spec(world: WorldSpec, config: RunConfig, catalogue: tuple[AssetModel, ...], shades: dict) -> mujoco.MjSpec:
    by_name = {m.name: m for m in catalogue}
    drone, cam = config.drone, config.camera
    half = world.field_size / 2
    pitch = math.radians(cam.pitch_deg)
    # Inertia of a 1 kg quadrotor frame scaled with the arm length (a flat cross plus a central box).
    ixx = 0.25 * drone.mass * drone.arm_length**2
    xml = _BASE_XML.format(
        dt=drone.physics_dt, g=GRAVITY, shadow_size=cam.shadow_size, offsamples=4 if cam.msaa else 0,
        offwidth=max(1024, cam.width), offheight=max(1024, cam.height), shadows=str(cam.shadows).lower(),
        half=half, outside=4 * world.field_size, topdown=TOPDOWN_CAMERA, topdown_extent=topdown_extent(world),
        altitude=drone.altitude, mass=drone.mass, ixx=ixx, izz=2 * ixx, arms=_arms_xml(drone.arm_length),
        fpv=FPV_CAMERA, cam_forward=cam.forward_offset, sp=math.sin(pitch), cp=math.cos(pitch),
        fovy=cam.vfov_deg, max_thrust=3 * drone.mass * GRAVITY, head_ambient=f"{HEADLIGHT[0]} " * 3,
        head_diffuse=f"{HEADLIGHT[1]} " * 3,
        sun=SUN, sun_blue=SUN - 0.03, sun_dir=" ".join(map(str, SUN_DIR)), **_field_texture(cam))
    spec = mujoco.MjSpec.from_string(xml)
    for i, lm in enumerate(world.landmarks):
        model = by_name[lm.model]
        body = spec.worldbody.add_body(name=f"landmark_{i}", pos=[lm.x, lm.y, 0.0],
                                       quat=_yaw_quat(lm.yaw))
        for k, part in enumerate(model.parts):
            vertices, faces, shade = shades.get((i, k), (part.vertices, part.faces, None))
            pieces = [(1.0, faces)] if shade is None else [  # baked: its shadowed faces darker, a geom per shade
                (float(f), faces[shade == f]) for f in np.unique(shade)]
            for n, (factor, faces) in enumerate(pieces):
                suffix = "" if n == 0 else f"_shade_{n}"
                mesh = spec.add_mesh(name=f"landmark_{i}_part_{k}{suffix}")
                mesh.uservert = np.asarray(vertices).ravel().tolist()
                mesh.userface = faces.ravel().tolist()
                mesh.scale = [lm.scale] * 3
                mesh.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL  # scenery: never simulated
                rgba = [*(c * factor for c in part.rgba[:3]), part.rgba[3]]
                body.add_geom(name=f"landmark_{i}_geom_{k}{suffix}", type=mujoco.mjtGeom.mjGEOM_MESH,
                              meshname=mesh.name, rgba=rgba, contype=0, conaffinity=0)
    for i, lake in enumerate(world.lakes):
        spec.worldbody.add_geom(name=f"lake_{i}", type=mujoco.mjtGeom.mjGEOM_ELLIPSOID,
                                size=[lake.radius_x, lake.radius_y, 0.015], pos=[lake.x, lake.y, 0.0],
                                quat=_yaw_quat(lake.yaw), material="water", contype=0, conaffinity=0)
    return spec


def _field_texture(cam: CameraConfig) -> dict[str, object]:
    """The field's material: the grass checker repeated, or with baked shadows one texture over the whole field
    (filled by gsmn.world.shadows.bake)."""
    if not cam.baked_shadows:
        return {"field_texture": "", "field_material_texture": shadows.GRASS_TEXTURE,
                "field_repeat": shadows.GRASS_REPEAT}
    side = 64 * shadows.GRASS_REPEAT  # the grass checker's texels (width="64" above) over the field
    return {"field_texture": f'<texture name="{shadows.FIELD_TEXTURE}" type="2d" builtin="flat" rgb1="1 1 1" '
                             f'width="{side}" height="{side}"/>',
            "field_material_texture": shadows.FIELD_TEXTURE, "field_repeat": 1}


def _yaw_quat(yaw: float) -> list[float]:
    return [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]


def topdown_extent(world: WorldSpec) -> float:
    """Side (m) of the square the orthographic top-down camera sees: the field plus a 1 m border."""
    return world.field_size + 2


def topdown_pixel(world: WorldSpec, x: float, y: float, size: int) -> tuple[float, float]:
    """Pixel (u, v) of world point (x, y) in `Simulator.render_topdown(size)`; north (+y) is up."""
    extent, half = topdown_extent(world), world.field_size / 2
    return ((x - half) / extent + 0.5) * size, (0.5 - (y - half) / extent) * size


def quat_to_R(quat: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of a MuJoCo quaternion (w, x, y, z)."""
    R = np.empty(9)
    mujoco.mju_quat2Mat(R, np.asarray(quat, dtype=float))
    return R.reshape(3, 3)


def yaw_of(R_world_body: np.ndarray) -> float:
    return math.atan2(R_world_body[1, 0], R_world_body[0, 0])


class DroneController:
    """Cascaded controller: (forward velocity, yaw rate) command -> (thrust, roll, pitch, yaw torques).

    Outer loops (velocity in the heading frame, altitude) give a desired thrust vector; its direction is
    the desired body z axis, tracked by a PD attitude loop; yaw rate is tracked by a P loop on the body
    rate. Gains are in units of the loop's natural dynamics and scaled by the body's mass and inertia.
    """

    def __init__(self, config: DroneConfig, inertia: np.ndarray):
        self.config = config
        self.inertia = np.asarray(inertia, dtype=float)  # principal moments (3,)
        self.max_tilt_acc = GRAVITY * math.tan(math.radians(config.max_tilt_deg))

    def __call__(self, qpos: np.ndarray, qvel: np.ndarray, v_cmd: float, omega_cmd: float) -> np.ndarray:
        """(thrust, torque x, y, z). Written on Python floats, not 3-vectors: it runs 40 times a step, where numpy's
        per-call cost made it a fifth of a live step. The arithmetic is the vector form's, term for term
        (tests/test_world.py keeps that form as the reference); Python floats never fuse a multiply and an add,
        so these bits are the same on every CPU, where numpy's products (OpenBLAS) may fuse them on one with FMA
        and differ from the float form in the last bits of rounding."""
        c = self.config
        R = quat_to_R(qpos[3:7])  # R_world_body
        yaw = yaw_of(R)
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = R.ravel().tolist()  # row by row
        cos_yaw, sin_yaw = math.cos(yaw), math.sin(yaw)  # fwd = (cos, sin, 0), left = (-sin, cos, 0)
        vx, vy, vz, wx, wy, wz = qvel[0:6].tolist()  # world velocity, body rates
        # Velocity loop in the heading frame: no lateral velocity is ever commanded. The heading frame turns
        # at the yaw rate, so holding v_cmd along it needs the centripetal acceleration omega * v_cmd.
        yaw_rate = r20 * wx + r21 * wy + r22 * wz
        lim = self.max_tilt_acc
        a_fwd = min(max(c.velocity_gain * (v_cmd - (vx * cos_yaw + vy * sin_yaw + vz * 0.0)), -lim), lim)
        a_left = min(max(c.velocity_gain * (0.0 - (vx * -sin_yaw + vy * cos_yaw + vz * 0.0)) + yaw_rate * v_cmd,
                         -lim), lim)
        a_up = c.altitude_kp * (c.altitude - float(qpos[2])) - c.altitude_kd * vz
        tx = c.mass * ((a_fwd * cos_yaw + a_left * -sin_yaw) + 0.0)  # the desired thrust, world frame
        ty = c.mass * ((a_fwd * sin_yaw + a_left * cos_yaw) + 0.0)
        tz = c.mass * ((a_fwd * 0.0 + a_left * 0.0) + (GRAVITY + a_up))
        thrust = max(0.0, tx * r02 + ty * r12 + tz * r22)  # along the body z axis (R's last column)
        # Attitude loop: rotate the body z axis onto the desired thrust direction, while the body turns
        # at the commanded world yaw rate. Rates are damped relative to that reference rotation (so a
        # steady banked turn needs no correcting torque), and the gyroscopic term is fed forward.
        norm = math.sqrt(tx * tx + ty * ty + tz * tz)
        dx, dy, dz = tx / norm, ty / norm, tz / norm
        cx, cy, cz = r12 * dz - r22 * dy, r22 * dx - r02 * dz, r02 * dy - r12 * dx  # z_body x z_des
        err_x = r00 * cx + r10 * cy + r20 * cz  # R^T (z_body x z_des)
        err_y = r01 * cx + r11 * cy + r21 * cz
        ref_x = r00 * 0.0 + r10 * 0.0 + r20 * omega_cmd  # R^T (0, 0, omega_cmd)
        ref_y = r01 * 0.0 + r11 * 0.0 + r21 * omega_cmd
        ref_z = r02 * 0.0 + r12 * 0.0 + r22 * omega_cmd
        ix, iy, iz = self.inertia.tolist()
        torque_x = ix * (c.attitude_kp * err_x + c.attitude_kd * (ref_x - wx))
        torque_y = iy * (c.attitude_kp * err_y + c.attitude_kd * (ref_y - wy))
        torque_z = iz * (c.yaw_rate_gain * (ref_z - wz))
        hx, hy, hz = ix * wx, iy * wy, iz * wz  # angular momentum: omega x (I omega) fed forward
        return np.array([thrust, torque_x + (wy * hz - wz * hy), torque_y + (wz * hx - wx * hz),
                         torque_z + (wx * hy - wy * hx)])


_STATE = mujoco.mjtState.mjSTATE_INTEGRATION


class Simulator:
    """Owns one compiled world, its physics state, and the renderer."""

    def __init__(self, world: WorldSpec, config: RunConfig, catalogue: tuple[AssetModel, ...] | None = None):
        self.world = world
        self.config = config
        self.model = build_spec(world, config, catalogue).compile()
        self.data = mujoco.MjData(self.model)
        self._drone_body = self.model.body("drone").id
        self._fpv = self.model.camera(FPV_CAMERA).id
        self._gimbal = self.model.body("gimbal").mocapid[0]
        self.controller = DroneController(config.drone, self.model.body_inertia[self._drone_body])
        self.K = intrinsics(config.camera)
        self._renderers: dict[tuple[int, int], mujoco.Renderer] = {}
        self.reset()
        self._baked = config.camera.baked_shadows
        if self._baked:  # before any renderer uploads the model's textures and lights
            shadows.bake(self.model, self.data, world.field_size, config.camera.pitch_deg)
            shadows.scale_lights(self.model)

    # -- state -------------------------------------------------------------------------------------
    def reset(self) -> None:
        w, c = self.world, self.config.drone
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[0:3] = [w.start_x, w.start_y, c.altitude]
        self.data.qpos[3:7] = _yaw_quat(w.start_yaw)
        self._settle()

    def _settle(self) -> None:
        """Move the gimbal to the drone and recompute kinematics, so that poses, camera and rendering all
        reflect the current state (after mj_step, MuJoCo's kinematic quantities lag qpos by one step)."""
        d = self.data
        d.mocap_pos[self._gimbal] = d.qpos[0:3]
        d.mocap_quat[self._gimbal] = _yaw_quat(self.yaw)
        mujoco.mj_forward(self.model, d)

    def get_state(self) -> np.ndarray:
        """The physics state that determines every later step (MuJoCo's integration state: time, qpos, qvel,
        act, the warm start, controls and mocap poses), float64, a few hundred bytes."""
        out = np.empty(mujoco.mj_stateSize(self.model, _STATE))
        mujoco.mj_getState(self.model, self.data, out, _STATE)
        return out

    def set_state(self, state: np.ndarray) -> None:
        """Put the physics back in a state from `get_state`; the steps from it repeat those flown from it."""
        if state.shape != (mujoco.mj_stateSize(self.model, _STATE),):
            raise ValueError(f"a state of this world has {mujoco.mj_stateSize(self.model, _STATE)} numbers, got "
                             f"{state.shape}")
        mujoco.mj_setState(self.model, self.data, np.asarray(state, dtype=float), _STATE)
        mujoco.mj_forward(self.model, self.data)

    def drone_state(self) -> dict[str, np.ndarray]:
        """The physics state without the landmarks' (static bodies: their part is the zero forces applied to them),
        which carries over to a world with other landmarks (`set_drone_state`): world edits at a fork's step."""
        d = self.data
        return {"time": np.array([d.time]), "qpos": d.qpos.copy(), "qvel": d.qvel.copy(), "act": d.act.copy(),
                "qacc_warmstart": d.qacc_warmstart.copy(), "ctrl": d.ctrl.copy(), "qfrc_applied": d.qfrc_applied.copy(),
                "xfrc_applied": d.xfrc_applied[self._drone_body].copy(), "mocap_pos": d.mocap_pos.copy(),
                "mocap_quat": d.mocap_quat.copy()}

    def set_drone_state(self, state: dict[str, np.ndarray]) -> None:
        d = self.data
        d.time = float(state["time"][0])
        for name in ("qpos", "qvel", "act", "qacc_warmstart", "ctrl", "qfrc_applied", "mocap_pos", "mocap_quat"):
            getattr(d, name)[...] = state[name]
        d.xfrc_applied[...] = 0.0
        d.xfrc_applied[self._drone_body] = state["xfrc_applied"]
        mujoco.mj_forward(self.model, d)

    def step(self, forward_velocity: float, yaw_rate: float) -> None:
        """Hold one (clipped) command for 1 / control_hz seconds of physics."""
        c = self.config.drone
        v = float(np.clip(forward_velocity, 0.0, c.max_forward_velocity))  # no reversing
        w = float(np.clip(yaw_rate, -c.max_yaw_rate, c.max_yaw_rate))
        m, d = self.model, self.data
        for _ in range(c.substeps):
            d.ctrl[:] = self.controller(d.qpos, d.qvel, v, w)
            mujoco.mj_step(m, d)
        self._settle()

    @property
    def time(self) -> float:
        return float(self.data.time)

    @property
    def position(self) -> np.ndarray:
        return self.data.qpos[0:3].copy()

    @property
    def R_world_body(self) -> np.ndarray:
        return quat_to_R(self.data.qpos[3:7])

    @property
    def yaw(self) -> float:
        return yaw_of(self.R_world_body)

    @property
    def velocity_world(self) -> np.ndarray:
        return self.data.qvel[0:3].copy()

    @property
    def yaw_rate(self) -> float:
        """Angular velocity about the world z axis (rad/s)."""
        return float((self.R_world_body @ self.data.qvel[3:6])[2])

    @property
    def T_world_camera(self) -> np.ndarray:
        """Pose (4, 4) of the forward camera in the computer-vision convention (x right, y down, z fwd)."""
        T = np.eye(4)
        T[:3, :3] = self.data.cam_xmat[self._fpv].reshape(3, 3) @ R_GL_CV
        T[:3, 3] = self.data.cam_xpos[self._fpv]
        return T

    # -- rendering ---------------------------------------------------------------------------------
    def _get_renderer(self, height: int, width: int) -> mujoco.Renderer:
        r = self._renderers.get((height, width))
        if r is None:
            try:
                r = self._renderers[(height, width)] = mujoco.Renderer(self.model, height, width)
            except mujoco.FatalError as e:
                raise RuntimeError(
                    f"MuJoCo could not create an OpenGL context ({e}). Rendering here is headless through EGL: "
                    "set MUJOCO_GL=egl in the environment, or import gsmn before mujoco (gsmn sets it).") from e
            r.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = self.config.camera.shadows and not self._baked
        return r

    def _finish(self, image: np.ndarray) -> np.ndarray:
        return shadows.restore(image) if self._baked else image

    def render(self) -> np.ndarray:
        """The forward camera image (H, W, 3) uint8, top row first."""
        cam = self.config.camera
        r = self._get_renderer(cam.height, cam.width)
        r.update_scene(self.data, camera=self._fpv)
        return self._finish(r.render())

    def render_segmentation(self) -> np.ndarray:
        """Per-pixel MuJoCo geom id (H, W) int of the forward camera (-1 for the sky)."""
        cam = self.config.camera
        r = self._get_renderer(cam.height, cam.width)
        r.enable_segmentation_rendering()
        try:
            r.update_scene(self.data, camera=self._fpv)
            seg = r.render()
        finally:
            r.disable_segmentation_rendering()
        return np.where(seg[..., 1] == mujoco.mjtObj.mjOBJ_GEOM, seg[..., 0], -1)

    def render_topdown(self, size: int = 512) -> np.ndarray:
        """An orthographic view straight down on the field (size, size, 3) uint8; north (+y) up."""
        r = self._get_renderer(size, size)
        r.update_scene(self.data, camera=TOPDOWN_CAMERA)
        return self._finish(r.render())

    def landmark_of_geom(self, geom_id: int) -> int | None:
        """Index into world.landmarks of the landmark a geom belongs to, or None."""
        if geom_id < 0:
            return None
        name = self.model.body(self.model.geom_bodyid[geom_id]).name
        return int(name.split("_")[1]) if name.startswith("landmark_") else None

    def close(self) -> None:
        for r in self._renderers.values():
            r.close()
        self._renderers.clear()

    def __del__(self) -> None:  # best effort: free the GL context
        try:
            self.close()
        except Exception:
            pass
