"""The 3D scene (viser): the world with the simulator's own meshes, the task (demonstration path, goal, the
success region with its correct quadrant), the drone with its camera frustum showing the live image, the
flown path, and the model's maps as images on the ground. In presenter mode a yellow ring and a "drone" label mark
the drone, so that an audience finds it on the field.

Frames: world x east, y north, z up (docs/design.md). Maps are north-up pictures (row 0 at y = 30), placed on
the field by a half-turn about x, since viser draws an image's row 0 towards local -y. Colours follow the
paper's figures: demonstration red, policy blue, success quadrant green; the counterfactual's goal is gold
(`app.render.colors`, which has their legend).
"""

from __future__ import annotations

import math

import numpy as np
import viser

from app.render.colors import (
    COUNTERFACTUAL_RGB,
    DEMO_RGB,
    DRONE_MARK_RGB,
    POLICY_RGB,
    QUADRANT_RGB,
    decode_image,
    png_bytes,
    upscale,
    with_alpha,
)
from gsmn.task.instructions import Instruction
from gsmn.world.assets import AssetModel
from gsmn.world.spec import WorldSpec

DRONE_MARK_RADIUS = 1.2  # m, presenter mode's ring around the drone (its body is 0.5 m long)
MAP_UPSCALE = 8  # 32 x 32 cells -> 256 x 256 pixels: sharp cells despite the texture's linear filtering
LAYER_HEIGHTS = {"semantic": 0.03, "relevance": 0.05, "goal": 0.07}  # any other layer: just below the semantic map
OTHER_LAYER_HEIGHT = 0.02
SIDES_HEIGHT = 0.1  # the four sides drawn while an instruction is typed: above every layer
WHATIF_QUADRANT_HEIGHT = 0.018  # not at OTHER_LAYER_HEIGHT: two surfaces at one height fight for depth
NORTH_UP = (0.0, 1.0, 0.0, 0.0)  # half-turn about x: image row 0 (local -y) to world +y (north)
TASK_PARTS = ("region", "ring", "quadrant", "goal", "goal_label", "demo")
# The 3D view's first camera: over the field from beyond the middle of its south edge (viser's vertical field of
# view), so that all four corners, where episodes start, fit a canvas down to 0.64 wide per unit of height (1280 x
# 800 between the side panels) with the drone's frustum; from beyond the south-west corner the south-east start
# corner and the drone were cut off at the right edge.
DEFAULT_CAMERA = {"position": (15.0, -20.0, 32.0), "look_at": (15.0, 12.0, 0.0), "up": (0.0, 0.0, 1.0),
                  "fov": math.radians(75.0)}
# The depth range. viser's own (0.01 to 1000 m) leaves a 24-bit depth buffer about 1 cm of resolution at 40 m,
# which is where the field is seen from: the ground's stacked surfaces (field, grid, lakes, region, the map layers
# 2 cm apart) fought for depth seen from near top-down, one triangle of a layer showing over another. From 0.5 m
# it is 0.2 mm, and nothing is looked at from closer than the drone's frustum.
CAMERA_NEAR, CAMERA_FAR = 0.5, 400.0
LABEL_GAP = 0.6  # m from a landmark's top to its label
LABEL_STEP = 0.5  # m a label rises at a time to clear another
LABEL_MAX_RISE = 8.0
LABEL_PX = {"char": 6.5, "pad": 10.0, "height": 18.0, "viewport": 900.0}  # a viser label at screen scale 1


def yaw_wxyz(yaw: float) -> tuple[float, float, float, float]:
    return (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))


def R_to_wxyz(R: np.ndarray) -> np.ndarray:
    """Quaternion (w, x, y, z) of a rotation matrix."""
    import mujoco

    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.asarray(R, dtype=float).ravel())
    return q


def _rgb(rgba: tuple[float, ...]) -> tuple[int, int, int]:
    return tuple(int(round(255 * c)) for c in rgba[:3])


def draw_world(scene: viser.SceneApi, world: WorldSpec, catalogue: tuple[AssetModel, ...], generation: int = 0) -> str:
    """(Re)draw field, lakes and landmarks under /world; replaces what was there. Returns the folder the landmarks
    are under: a new name each `generation`, since a landmark drawn under the name another world's landmark had
    just been removed from sometimes never showed in the page (viser culls a pending removal and a creation of one
    name against each other; seen in environment 76 after 70: the cone's label without its mesh)."""
    by_name = {m.name: m for m in catalogue}
    L = world.field_size
    if _has(scene, "/world"):
        scene.remove_by_name("/world")
    scene.add_frame("/world", show_axes=False)  # children are placed relative to their parent
    scene.add_box("/world/field", color=(92, 150, 62), dimensions=(L, L, 0.02), position=(L / 2, L / 2, -0.011),
                  flat_shading=True, cast_shadow=False)
    scene.add_grid("/world/grid", width=L, height=L, cell_size=1.5, section_size=7.5, position=(L / 2, L / 2, 0.002),
                   cell_color=(84, 140, 58), section_color=(70, 118, 48), shadow_opacity=0.0)
    for i, lake in enumerate(world.lakes):
        verts, faces = _fan(np.zeros(2), lake.radius_x, lake.radius_y, 0.0, 2 * math.pi, 48, 0.005)
        scene.add_mesh_simple(f"/world/lake_{i}", verts, faces, color=(51, 107, 191), wxyz=yaw_wxyz(lake.yaw),
                              position=(lake.x, lake.y, 0.0), cast_shadow=False)
    landmarks = f"/world/landmarks_{generation}"
    scene.add_frame(landmarks, show_axes=False)
    for i, lm in enumerate(world.landmarks):
        model = by_name[lm.model]
        frame = f"{landmarks}/landmark_{i}"
        scene.add_frame(frame, show_axes=False, wxyz=yaw_wxyz(lm.yaw), position=(lm.x, lm.y, 0.0))
        for k, part in enumerate(model.parts):
            scene.add_mesh_simple(f"{frame}/part_{k}", part.vertices, part.faces, color=_rgb(part.rgba),
                                  scale=lm.scale, flat_shading=True)
    tops = [by_name[lm.model].height * lm.scale for lm in world.landmarks]
    heights = label_heights([(lm.x, lm.y, top) for lm, top in zip(world.landmarks, tops, strict=True)],
                            [lm.noun_phrase for lm in world.landmarks])
    for i, (lm, top, z) in enumerate(zip(world.landmarks, tops, heights, strict=True)):
        scene.add_label(f"{landmarks}/label_{i}", lm.noun_phrase, position=(lm.x, lm.y, z), anchor="bottom-center")
        if z > top + LABEL_GAP + 1e-6:  # raised to clear another label: a thin stem says whose it is
            stem = np.array([[[lm.x, lm.y, top + 0.1], [lm.x, lm.y, z]]])
            scene.add_line_segments(f"{landmarks}/label_stem_{i}", stem, colors=(90, 90, 90), line_width=1.5)
    return landmarks


def label_box(point: tuple[float, float, float], text: str, camera: dict = DEFAULT_CAMERA
              ) -> tuple[float, float, float, float] | None:
    """The pixel box (left, top, right, bottom; from the view's centre, y down) of a viser label anchored
    bottom-centre at `point`, at screen scale 1 on a 900-pixel-high view from `camera`; None behind it."""
    eye, target, up = (np.asarray(camera[k], dtype=float) for k in ("position", "look_at", "up"))
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    focal = LABEL_PX["viewport"] / 2 / math.tan(camera["fov"] / 2)
    d = np.asarray(point, dtype=float) - eye
    depth = d @ forward
    if depth <= 0.1:
        return None
    u, v = focal * (d @ right) / depth, focal * (d @ down) / depth
    w = LABEL_PX["char"] * len(text) + LABEL_PX["pad"]
    return u - w / 2, v - LABEL_PX["height"], u + w / 2, v


def in_view(point: tuple[float, float, float], camera: dict, aspect: float, margin: float = 1.0) -> bool:
    """Whether a world point lies inside `margin` of the view from `camera` (viser's vertical field of view) on a
    canvas `aspect` wide per unit of height."""
    eye, target, up = (np.asarray(camera[k], dtype=float) for k in ("position", "look_at", "up"))
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    d = np.asarray(point, dtype=float) - eye
    depth = d @ forward
    half = math.tan(camera["fov"] / 2) * margin
    return bool(depth > 0 and abs(d @ down) <= half * depth and abs(d @ right) <= half * aspect * depth)


def framing_camera(aspect: float, field_size: float = 30.0, margin: float = 0.9, top: float = 4.0) -> dict:
    """The first camera's view brought as close as the field allows on a canvas `aspect` wide per unit of height:
    the same direction, the nearest distance (to 1 %) at which the field's corners, and points `top` m above
    them, stay within `margin` of the view. Presenter mode's 3D view, wider than the page's, so fills with the
    field rather than with sky."""
    target = np.asarray(DEFAULT_CAMERA["look_at"], dtype=float)
    away = np.asarray(DEFAULT_CAMERA["position"], dtype=float) - target
    corners = [(x, y, z) for x in (0.0, field_size) for y in (0.0, field_size) for z in (0.0, top)]

    def camera(scale: float) -> dict:
        return {**DEFAULT_CAMERA, "position": tuple((target + scale * away).tolist())}

    near, far = 0.2, 3.0  # fractions of the first camera's distance; far always fits (the corners are in view)
    while far - near > 0.01:
        mid = (near + far) / 2
        if all(in_view(c, camera(mid), aspect, margin) for c in corners):
            far = mid
        else:
            near = mid
    return camera(far)


def boxes_overlap(a: tuple[float, float, float, float] | None, b: tuple[float, float, float, float] | None) -> bool:
    return a is not None and b is not None and a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def label_heights(tops: list[tuple[float, float, float]], texts: list[str],
                  camera: dict = DEFAULT_CAMERA) -> list[float]:
    """Heights for labels (anchored bottom-centre) above points `tops` so that, seen from the 3D view's first
    camera, no two overlap: labels nearer the camera keep their place (LABEL_GAP above the top) and each farther
    one rises by LABEL_STEP until its box is clear (at most LABEL_MAX_RISE). A rotated camera can still see
    labels overlap."""
    eye = np.asarray(camera["position"], dtype=float)
    heights = [top[2] + LABEL_GAP for top in tops]
    placed: list[tuple[float, float, float, float]] = []
    for i in sorted(range(len(tops)), key=lambda i: float(np.linalg.norm(np.asarray(tops[i]) - eye))):
        x, y, top = tops[i]
        z = top + LABEL_GAP
        box = label_box((x, y, z), texts[i], camera)
        while any(boxes_overlap(box, p) for p in placed) and z < top + LABEL_GAP + LABEL_MAX_RISE:
            z += LABEL_STEP
            box = label_box((x, y, z), texts[i], camera)
        heights[i] = z
        if box is not None:
            placed.append(box)
    return heights


def _has(scene: viser.SceneApi, name: str) -> bool:
    return name in getattr(scene, "_handle_from_node_name", {})


def _fan(centre: np.ndarray, rx: float, ry: float, start: float, end: float, n: int, z: float
         ) -> tuple[np.ndarray, np.ndarray]:
    """A filled ellipse sector as a triangle fan: vertices (n + 2, 3) float32, faces (n, 3) int32."""
    t = np.linspace(start, end, n + 1)
    rim = np.stack([centre[0] + rx * np.cos(t), centre[1] + ry * np.sin(t), np.full(n + 1, z)], 1)
    verts = np.vstack([[centre[0], centre[1], z], rim]).astype(np.float32)
    faces = np.array([[0, 1 + k, 2 + k] for k in range(n)], dtype=np.int32)
    return verts, faces


SIDE_TURN = {"back": 0.0, "front": math.pi, "left": math.pi / 2, "right": -math.pi / 2}
SIDES_RGB = {"left": (80, 150, 230), "right": (230, 120, 60), "front": (200, 200, 80), "back": (170, 90, 200)}
SIDE_PARTS = ("from_start", *(f"{side}{part}" for side in SIDE_TURN for part in ("", "_label")))


def side_angles(world: WorldSpec, landmark_index: int, side: str) -> tuple[float, float]:
    """One side's quadrant around a landmark as (start, end) angles, counter-clockwise (gsmn.task.metrics.side_of:
    back around d = landmark - start, front around -d, left counter-clockwise)."""
    lm = world.landmarks[landmark_index]
    d = math.atan2(lm.y - world.start_y, lm.x - world.start_x)
    centre = d + SIDE_TURN[side]
    return centre - math.pi / 4, centre + math.pi / 4


def quadrant_angles(world: WorldSpec, instruction: Instruction) -> tuple[float, float]:
    """The success quadrant of an instruction around its landmark as (start, end) angles, counter-clockwise."""
    return side_angles(world, instruction.landmark_index, instruction.side)


def _segments(points: np.ndarray) -> np.ndarray:
    """Polyline (N, 3) -> segments (N - 1, 2, 3)."""
    return np.stack([points[:-1], points[1:]], 1).astype(np.float32)


def set_png(handle: viser.ImageHandle, rgba: np.ndarray) -> None:
    """Replace a scene image with a PNG encoded by Pillow at low compression: viser's own encoder (imageio) takes
    about 5 ms for a 256 x 256 map and Pillow 1.3 ms, and the page draws three maps a step. The handle's
    `_image` / `_data` are what viser's own `image` setter assigns (viser 1.1)."""
    handle._image = rgba
    handle._data = png_bytes(rgba)


def set_frustum_jpeg(handle: viser.CameraFrustumHandle, jpeg: bytes) -> None:
    """Show an already encoded JPEG in a camera frustum: the runner encodes every camera image once, and viser's
    own setter would encode the pixels again (through imageio, after trying to import cv2 on every call).
    `_format` / `_image_data` are the props viser's `image` setter assigns (viser 1.1)."""
    handle._format = "jpeg"
    handle._image_data = jpeg


class SceneView:
    """The dynamic parts of one tab's scene, by name. All methods expect to be called inside `client.atomic()`.
    `client`: a viser ClientHandle (or the server, for a scene every tab shares)."""

    def __init__(self, client: viser.ClientHandle | viser.ViserServer, catalogue: tuple[AssetModel, ...],
                 success_radius: float, vfov_deg: float, aspect: float):
        self.scene = client.scene
        self.catalogue = catalogue
        self.success_radius = success_radius
        self.vfov = math.radians(vfov_deg)
        self.aspect = aspect
        self.layers: dict[str, viser.ImageHandle] = {}
        self.frustum: viser.CameraFrustumHandle | None = None
        self.body = None
        self.world: WorldSpec | None = None
        self.show_task = True
        self.task: Instruction | None = None  # the instruction whose goal is drawn (`draw_task`)
        self.goal_label = "goal"
        self.generation = 0  # of the landmarks drawn (`draw_world`)
        self.drone_marked = False  # presenter mode: a ring and a label on the drone
        self.mark: viser.FrameHandle | None = None

    def draw_world(self, world: WorldSpec, on_ground_click=None, on_landmark_click=None) -> None:
        """The world; `on_ground_click(x, y)` is called with the ground point of a click on the field,
        `on_landmark_click(name, index)` with the name and index of a landmark clicked."""
        self.generation += 1
        landmarks = draw_world(self.scene, world, self.catalogue, self.generation)
        self.world = world
        if on_landmark_click is not None:
            handles = self.scene._handle_from_node_name
            for i, lm in enumerate(world.landmarks):
                for name, handle in list(handles.items()):
                    if name.startswith(f"{landmarks}/landmark_{i}/part_"):
                        handle.on_click(lambda _, phrase=lm.noun_phrase, i=i: on_landmark_click(phrase, i))
        if on_ground_click is not None:
            field = self.scene._handle_from_node_name.get("/world/field")

            @field.on_click
            def _(event: viser.SceneNodePointerEvent) -> None:
                (ox, oy, oz), (dx, dy, dz) = event.ray_origin, event.ray_direction
                if dz < -1e-6:  # the ray meets the ground z = 0 in front of the camera
                    t = -oz / dz
                    on_ground_click(ox + t * dx, oy + t * dy)
        self.layers.clear()  # they lived under /world
        self.clear_path()
        self.draw_counterfactual(None)

    def draw_task(self, instruction: Instruction | None, path: np.ndarray | None, prefix: str = "/task",
                  rgb: tuple[int, int, int] = QUADRANT_RGB) -> None:
        """The named landmark's success region (radius 6 m) with the correct quadrant, the goal and the
        demonstration path; None clears them."""
        for name in TASK_PARTS:
            if _has(self.scene, f"{prefix}/{name}"):
                self.scene.remove_by_name(f"{prefix}/{name}")
        if prefix == "/task":
            self.task, self.goal_label = instruction, "goal"
        if instruction is None or self.world is None:
            return
        world, r = self.world, self.success_radius
        lm = world.landmarks[instruction.landmark_index]
        centre = np.array([lm.x, lm.y])
        if prefix == "/task":
            verts, faces = _fan(centre, r, r, 0.0, 2 * math.pi, 64, 0.012)
            self.scene.add_mesh_simple(f"{prefix}/region", verts, faces, color=(235, 235, 235), opacity=0.22,
                                       cast_shadow=False, receive_shadow=False, visible=self.show_task)
            ring = verts[1:].copy()
            ring[:, 2] = 0.09
            self.scene.add_line_segments(f"{prefix}/ring", _segments(ring), (255, 255, 255), thickness=0.1,
                                         visible=self.show_task)
        a0, a1 = quadrant_angles(world, instruction)
        verts, faces = _fan(centre, r, r, a0, a1, 16, 0.016 if prefix == "/task" else WHATIF_QUADRANT_HEIGHT)
        self.scene.add_mesh_simple(f"{prefix}/quadrant", verts, faces, color=rgb, opacity=0.6, cast_shadow=False,
                                   receive_shadow=False, visible=self.show_task)
        self.scene.add_cylinder(f"{prefix}/goal", radius=0.25, height=2.0, color=rgb if prefix != "/task" else DEMO_RGB,
                                position=(instruction.goal_x, instruction.goal_y, 1.0), cast_shadow=False,
                                visible=self.show_task)
        self.scene.add_label(f"{prefix}/goal_label", "goal" if prefix == "/task" else "what-if goal",
                             position=(instruction.goal_x, instruction.goal_y, 2.3), anchor="bottom-center",
                             visible=self.show_task)
        if path is not None and len(path) > 1:
            points = np.column_stack([path, np.full(len(path), 0.1)])
            self.scene.add_line_segments(f"{prefix}/demo", _segments(points), DEMO_RGB, thickness=0.18,
                                         visible=self.show_task)

    def label_goal(self, typed: Instruction | None, anything_typed: bool) -> None:
        """The drawn goal's label says so when it is not the goal of the instruction typed (text that cannot be flown,
        or another instruction): the goal drawn is the world's own instruction's, or the episode's shown."""
        if self.task is None or not _has(self.scene, "/task/goal_label"):
            return
        same = not anything_typed or (typed is not None and typed.text == self.task.text)
        label = "goal" if same else "goal (not of the typed text)"
        if label != self.goal_label:
            self.goal_label = label
            self.scene.add_label("/task/goal_label", label, position=(self.task.goal_x, self.task.goal_y, 2.3),
                                 anchor="bottom-center", visible=self.show_task)

    def draw_sides(self, world: WorldSpec | None, instruction: Instruction | None = None) -> None:
        """While an instruction is typed: the four sides around the landmark it names, each labelled, the one asked
        stronger, and the line from the start that they are taken from (left and right as seen from the start);
        None clears them. This also marks which landmark an ambiguous name means."""
        for name in SIDE_PARTS:
            if _has(self.scene, f"/sides/{name}"):
                self.scene.remove_by_name(f"/sides/{name}")
        if world is None or instruction is None or world != self.world:
            return
        lm = world.landmarks[instruction.landmark_index]
        r = self.success_radius
        self.scene.add_line_segments("/sides/from_start", np.array([[[world.start_x, world.start_y, 0.2],
                                                                     [lm.x, lm.y, 0.2]]], np.float32),
                                     (255, 255, 255), thickness=0.15)
        for side in SIDE_TURN:
            a0, a1 = side_angles(world, instruction.landmark_index, side)
            verts, faces = _fan(np.array([lm.x, lm.y]), r, r, a0 + 0.03, a1 - 0.03, 12, SIDES_HEIGHT)
            asked = side == instruction.side
            self.scene.add_mesh_simple(f"/sides/{side}", verts, faces, color=SIDES_RGB[side],
                                       opacity=0.75 if asked else 0.35, cast_shadow=False, receive_shadow=False)
            mid = (a0 + a1) / 2
            self.scene.add_label(f"/sides/{side}_label", side.upper() if asked else side,
                                 position=(lm.x + 0.7 * r * math.cos(mid), lm.y + 0.7 * r * math.sin(mid), 0.4),
                                 anchor="center")

    def draw_counterfactual(self, instruction: Instruction | None) -> None:
        self.draw_task(instruction, None, prefix="/whatif", rgb=COUNTERFACTUAL_RGB)

    def set_task_visible(self, visible: bool) -> None:
        self.show_task = visible
        for prefix in ("/task", "/whatif"):
            for name in TASK_PARTS:
                handle = getattr(self.scene, "_handle_from_node_name", {}).get(f"{prefix}/{name}")
                if handle is not None:
                    handle.visible = visible

    def set_drone(self, position: tuple[float, float, float], yaw: float, T_world_camera: np.ndarray,
                  image: np.ndarray | None, jpeg: bytes | None = None) -> None:
        """Place the drone and its camera frustum showing `image`, or the same image already encoded (`jpeg`)."""
        wxyz, cam_position = R_to_wxyz(T_world_camera[:3, :3]), T_world_camera[:3, 3]
        if self.frustum is None or not _has(self.scene, "/drone/camera"):
            if image is None and jpeg is not None:
                image = decode_image(jpeg)
            self.frustum = self.scene.add_camera_frustum(
                "/drone/camera", fov=self.vfov, aspect=self.aspect, scale=1.6, thickness=0.05,
                image=image, format="jpeg", wxyz=wxyz, position=cam_position, color=(240, 120, 30))
            self.body = self.scene.add_box("/drone/body", color=(30, 30, 34), dimensions=(0.5, 0.36, 0.1),
                                           wxyz=yaw_wxyz(yaw), position=position)
            self._add_mark(position)
            return
        self.frustum.wxyz, self.frustum.position = wxyz, cam_position
        if jpeg is not None:
            set_frustum_jpeg(self.frustum, jpeg)
        elif image is not None:
            self.frustum.image = image
        self.body.wxyz, self.body.position = yaw_wxyz(yaw), position
        if self.mark is not None:
            self.mark.position = position

    def _add_mark(self, position: tuple[float, float, float]) -> None:
        """The drone's mark: a yellow ring around it, as wide on the screen at any distance, and a "drone" label
        above it; shown while `drone_marked`."""
        self.mark = self.scene.add_frame("/drone/mark", show_axes=False, position=position,
                                         visible=self.drone_marked)
        t = np.linspace(0.0, 2 * math.pi, 33)
        ring = np.column_stack([DRONE_MARK_RADIUS * np.cos(t), DRONE_MARK_RADIUS * np.sin(t), np.zeros_like(t)])
        self.scene.add_line_segments("/drone/mark/ring", _segments(ring), DRONE_MARK_RGB, thickness=5.0,
                                     thickness_units="screen")
        self.scene.add_label("/drone/mark/label", "drone", position=(0.0, 0.0, 0.9), anchor="bottom-center",
                             font_screen_scale=1.3)

    def mark_drone(self, on: bool) -> None:
        """Show or hide the drone's ring and label (presenter mode); remembered for a drone drawn later."""
        self.drone_marked = on
        if self.mark is not None and _has(self.scene, "/drone/mark"):
            self.mark.visible = on

    def set_path(self, positions: np.ndarray) -> None:
        """The flown path (N, 3); fewer than two points clears it."""
        if len(positions) < 2:
            self.clear_path()
            return
        points = np.asarray(positions, np.float32).copy()
        points[:, 2] = 0.14
        self.scene.add_line_segments("/flown", _segments(points), POLICY_RGB, thickness=0.2)

    def clear_path(self) -> None:
        if _has(self.scene, "/flown"):
            self.scene.remove_by_name("/flown")

    def set_layer(self, name: str, rgb: np.ndarray | None, alpha: np.ndarray | None, opacity: float,
                  visible: bool) -> None:
        """A map layer (H, W, 3) north-up on the field at its own height; `rgb` None only changes visibility."""
        handle = self.layers.get(name)
        if rgb is None:
            if handle is not None:
                handle.visible = visible
            return
        a = np.ones(rgb.shape[:2], np.float32) if alpha is None else alpha
        rgba = upscale(with_alpha(rgb, a * opacity), MAP_UPSCALE)
        if handle is None or not _has(self.scene, f"/world/map_{name}"):
            L = self.world.field_size if self.world else 30.0
            self.layers[name] = self.scene.add_image(
                f"/world/map_{name}", rgba, render_width=L, render_height=L, format="png", wxyz=NORTH_UP,
                position=(L / 2, L / 2, LAYER_HEIGHTS.get(name, OTHER_LAYER_HEIGHT)), cast_shadow=False,
                receive_shadow=False, visible=visible)
        else:
            set_png(handle, rgba)
            handle.visible = visible

    def mark_cell(self, xy: tuple[float, float] | None, cell_size: float) -> None:
        """Outline the inspected map cell on the ground (None removes it)."""
        if xy is None:
            if _has(self.scene, "/inspected"):
                self.scene.remove_by_name("/inspected")
            return
        x0, y0 = (np.floor(np.asarray(xy) / cell_size) * cell_size).tolist()
        corners = np.array([[x0, y0], [x0 + cell_size, y0], [x0 + cell_size, y0 + cell_size], [x0, y0 + cell_size],
                            [x0, y0]])
        points = np.column_stack([corners, np.full(5, 0.12)])
        self.scene.add_line_segments("/inspected", _segments(points), (255, 255, 255), thickness=0.12)

    def clear_layers(self) -> None:
        for name, handle in list(self.layers.items()):
            handle.remove()
            del self.layers[name]
