"""World preview in the browser (viser): the main command until the dashboard exists.

Pick an environment by id, by split or at random; the page shows the field with the simulator's own
landmark meshes, the drone at its start corner with its camera frustum, and the first camera image.
One runner thread owns the simulator and renderer (MuJoCo's GL context belongs to the thread that made
it); GUI callbacks only post commands to it.
"""

from __future__ import annotations

import queue
import threading

import numpy as np
import viser

from app.scene import R_to_wxyz, draw_world
from gsmn.config import RunConfig
from gsmn.world.assets import load_catalogue
from gsmn.world.env import Env
from gsmn.world.spec import SPLITS, split_env_ids, split_of


class Preview:
    def __init__(self, config: RunConfig, host: str = "127.0.0.1", port: int = 8080, env_id: int = 70):
        self.config = config
        self.catalogue = load_catalogue()
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.scene.set_up_direction("+z")
        camera = self.server.initial_camera  # looking over the field from beyond its south-west corner
        camera.position, camera.look_at, camera.up = (-12.0, -12.0, 26.0), (15.0, 15.0, 0.0), (0.0, 0.0, 1.0)
        self.commands: queue.Queue[int | None] = queue.Queue()
        self.rng = np.random.default_rng()
        self._build_gui(env_id)
        self.runner = threading.Thread(target=self._run, name="sim-runner", daemon=True)
        self.runner.start()
        self.commands.put(env_id)

    @property
    def url(self) -> str:
        return f"http://{self.server.get_host()}:{self.server.get_port()}"

    def _build_gui(self, env_id: int) -> None:
        gui = self.server.gui
        gui.add_markdown("### GSMN world preview\nThe dashboard will run episodes here.")
        self.env_number = gui.add_number("Environment id", env_id, min=0, step=1)
        self.split = gui.add_dropdown("Split", SPLITS, initial_value=split_of(env_id))
        show = gui.add_button("Show environment")
        random_button = gui.add_button("Random in split")
        self.status = gui.add_markdown("")
        self.camera_image = gui.add_image(np.zeros((144, 256, 3), np.uint8), label="Camera (first frame)",
                                          format="png")

        @show.on_click
        def _(_event) -> None:
            self.commands.put(int(self.env_number.value))

        @random_button.on_click
        def _(_event) -> None:
            index = int(self.rng.integers(0, 1000))
            env_id = split_env_ids(self.split.value, 1, start=index)[0]
            self.env_number.value = env_id
            self.commands.put(env_id)

    def _run(self) -> None:
        env = Env(self.config, self.catalogue)
        try:
            while (env_id := self.commands.get()) is not None:
                self._show(env, env_id)
        finally:
            env.close()

    def _show(self, env: Env, env_id: int) -> None:
        if env_id < 0:
            self.status.content = f"**Environment ids are non-negative**, got {env_id}."
            return
        obs = env.reset(env_id)
        world = env.world
        scene = self.server.scene
        with self.server.atomic():
            draw_world(scene, world, self.catalogue)
            T = obs.T_world_camera
            cam = self.config.camera
            scene.add_camera_frustum("/drone/camera", fov=np.radians(cam.vfov_deg), aspect=cam.width / cam.height,
                                     scale=1.2, image=obs.image, format="jpeg", wxyz=R_to_wxyz(T[:3, :3]),
                                     position=T[:3, 3], color=(240, 120, 30))
            scene.add_box("/drone/body", color=(30, 30, 34), dimensions=(0.36, 0.36, 0.08),
                          wxyz=R_to_wxyz(obs.pose.R_world_body), position=obs.pose.position)
        self.camera_image.image = obs.image
        names = ", ".join(lm.noun_phrase for lm in world.landmarks)
        self.status.content = (f"**Environment {env_id}** ({world.split} split): {len(world.landmarks)} landmarks: "
                               f"{names}.")

    def close(self) -> None:
        self.commands.put(None)
        self.runner.join(timeout=5)
        self.server.stop()
