"""`soma view --run RUN`: the model stepped in this process, teleoperated from the browser.

The same engine as soma_sim_node (:class:`~soma_ros.live.LiveSimulator`: the passive-object
rule, settling, the divergence check and its restart) steps at ``rate_hz`` in its own
thread from the joint vector the controls set:

* jog buttons move the tool centre by the step size along the simulation frame's axes,
  and a drag handle at the tool centre moves it anywhere (mouse teleop); both go through
  the robot's IK (:class:`~.teleop.EndEffectorJog`);
* open / close the gripper;
* reset: the initial scene again, the robot back at its start pose.

The robot starts with its tool centre above the object (``start_height_m`` along the up
direction, against gravity), gripper open.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Optional

import numpy as np

from .scene import TwinView, default_view_pose

__all__ = ["RunSource", "resolve_run"]


def resolve_run(run: str, scene: Optional[str] = None) -> tuple[Path, Path]:
    """(checkpoint, scene bundle dir) of RUN: a run directory (checkpoint.pt + scene/) or a checkpoint file."""
    p = Path(run)
    ckpt = p / "checkpoint.pt" if p.is_dir() else p
    if not ckpt.is_file():
        raise FileNotFoundError(f"no checkpoint at {ckpt} (give a `soma train` run directory or its checkpoint.pt)")
    sc = Path(scene) if scene else ckpt.parent / "scene"
    if not (sc / "scene.json").is_file():
        raise FileNotFoundError(f"no scene bundle at {sc} (scene.json missing; give --scene)")
    return ckpt, sc


class RunSource:
    """Steps a LiveSimulator and draws it on a TwinView (module docstring)."""

    def __init__(self, view: TwinView, run: str, scene: Optional[str] = None, rate_hz: float = 30.0,
                 draw_hz: float = 10.0, image_hz: float = 5.0, device: str = "cpu", start_height_m: float = 0.2,
                 settle_s: float = 2.0) -> None:
        from ..live import load_live
        from .teleop import EndEffectorJog

        ckpt, sc = resolve_run(run, scene)
        self.view = view
        self.live = load_live(str(ckpt), str(sc), device=device, settle_s=settle_s)
        live = self.live
        self.rate_hz, self.draw_hz, self.image_hz = float(rate_hz), float(draw_hz), float(image_hz)
        g = np.asarray(live.bundle.gravity, dtype=np.float64)
        self.up = -g / np.linalg.norm(g)
        M = np.asarray(live.base_to_sim.matrix(), dtype=np.float64)
        self.jog = EndEffectorJog(live.robot, M, live.required_joints, g)
        m = live.template.means.detach().double().cpu().numpy()
        self.center = m.mean(0)
        self.start_tcp = self.center + start_height_m * self.up
        err = self.jog.home(self.start_tcp)
        if err > 0.01:
            raise RuntimeError(f"the robot cannot put its gripper {start_height_m:.2f} m above the object "
                               f"(IK misses by {err * 1e3:.0f} mm)")
        self.start_q = self.jog.q.copy()
        self._vec = self.jog.joint_vector()
        self._vec_lock = threading.Lock()
        self.restarts = 0
        self.message = "ready"
        self._step_times: list[float] = []
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

        # ---- static layers
        base = M.copy()
        base[:3, :3] /= np.cbrt(np.linalg.det(base[:3, :3]))
        view.set_robot(Path(live.robot.config.urdf), base)
        view.set_table(live.bundle.table_normal, live.bundle.table_offset, self.center)
        target, eye = default_view_pose(self.center, M[:3, 3], self.up, radius=float(np.linalg.norm(m - m.mean(0), axis=1).max()))
        view.look_at(target, eye)
        self._controls()

    # ------------------------------------------------------------------ controls
    def _controls(self) -> None:
        gui = self.view.server.gui
        with gui.add_folder("Teleop"):
            self.step_cm = gui.add_slider("jog step (cm)", min=0.5, max=10.0, step=0.5, initial_value=2.0)
            for axis, name in enumerate("xyz"):
                group = gui.add_button_group(f"jog {name}", [f"-{name}", f"+{name}"])
                group.on_click(lambda ev, a=axis: self._on_jog(a, -1.0 if ev.target.value.startswith("-") else 1.0))
            grip = gui.add_button_group("gripper", ["open", "close"])
            grip.on_click(lambda ev: self._on_gripper(ev.target.value == "open"))
            gui.add_button("reset scene").on_click(lambda _: self.reset())
            self._msg = gui.add_markdown("")
        self.handle = self.view.server.scene.add_transform_controls(
            "/tcp_target", scale=0.12, disable_rotations=True, position=tuple(self.start_tcp))
        self.handle.on_update(lambda _: self._on_drag())

    def _apply(self, fn, what: str) -> None:
        from .teleop import JogRefused

        try:
            vec = fn()
        except JogRefused as exc:
            self.message = f"{what} refused: {exc}"
        else:
            with self._vec_lock:
                self._vec = vec
            self.message = f"{what}: tool centre at {np.round(self.jog.target, 3).tolist()}"
            self.handle.position = tuple(self.jog.target)
        self._msg.content = self.message

    def _on_jog(self, axis: int, sign: float) -> None:
        d = np.zeros(3)
        d[axis] = sign * float(self.step_cm.value) / 100.0
        self._apply(lambda: self.jog.jog(d), "jog")

    def _on_drag(self) -> None:
        target = np.asarray(self.handle.position, dtype=np.float64)
        if self.jog.target is not None and np.linalg.norm(target - self.jog.target) < 1e-4:
            return
        self._apply(lambda: self.jog.move_to(target), "move")

    def _on_gripper(self, open_: bool) -> None:
        self._apply(lambda: self.jog.set_gripper(open_), "gripper " + ("open" if open_ else "closed"))

    def reset(self) -> None:
        """The initial scene again and the robot at its start pose."""
        self.jog.q = self.start_q.copy()
        self.jog.target = self.start_tcp.copy()
        self.jog.set_gripper(True)
        with self._vec_lock:
            self._vec = self.jog.joint_vector()
            self.live.reset(self.live.bundle.splats)
        self.handle.position = tuple(self.start_tcp)
        self.message = "scene reset"
        self._msg.content = self.message

    def joint_vector(self) -> np.ndarray:
        with self._vec_lock:
            return self._vec.copy()

    # ------------------------------------------------------------------ loops
    def _every(self, hz: float, fn) -> None:
        period = 1.0 / hz
        t_next = time.monotonic()
        while not self._stop.is_set():
            fn()
            t_next += period
            delay = t_next - time.monotonic()
            if delay < 0:
                t_next = time.monotonic()
                delay = 0.0
            self._stop.wait(delay)

    def _step(self) -> None:
        with self._vec_lock:
            vec = self._vec.copy()
            try:
                self.live.step(vec)
                self._step_times.append(time.monotonic())
            except Exception as exc:  # noqa: BLE001 - as the node: report, restart from the initial scene
                self.restarts += 1
                self.message = f"step failed ({exc}); restarted from the initial scene"
                self.live.reset(self.live.template)

    def step_rate(self) -> float:
        now = time.monotonic()
        self._step_times = [t for t in self._step_times if now - t <= 1.0]
        return float(len(self._step_times) - 1) / max(now - self._step_times[0], 1e-9) if len(self._step_times) > 1 else 0.0

    def _draw(self, with_images: bool) -> None:
        state, template, steps = self.live.snapshot()
        vec = self.joint_vector()
        means = state.means.detach().float().cpu().numpy()
        covs = state.covs.detach().float().cpu().numpy()
        self.view.set_splats(means, covs, template.colors().detach().float().cpu().numpy(),
                             template.opacities.detach().float().cpu().numpy())
        self.view.set_joints(self.live.required_joints, vec)
        if with_images:
            out, cams = self.live.render(state, template, vec)
            rgb = out.rgb_u8().cpu().numpy()
            c2w = cams.cam_to_world().cpu().numpy()
            K = cams.K.cpu().numpy()
            for i, c in enumerate(self.live.cameras):
                self.view.set_camera(c.name, K[i], cams.width, cams.height, c2w[i], sim_image=rgb[i])
        self.view.set_status({"mode": "run (in-process model)", "splats": len(template), "steps": steps,
                              "step rate (Hz)": f"{self.step_rate():.1f} (target {self.rate_hz:.0f})",
                              "restarts": self.restarts, "settles": self.live.settles,
                              "gripper": "open" if self.jog.gripper_open else "closed"})

    def start(self) -> None:
        self._draw(with_images=True)
        last_img = [time.monotonic()]

        def draw() -> None:
            now = time.monotonic()
            imgs = self.image_hz > 0 and now - last_img[0] >= 1.0 / self.image_hz
            if imgs:
                last_img[0] = now
            try:
                self._draw(with_images=imgs)
            except Exception as exc:  # noqa: BLE001 - a failed draw must not stop the view
                self.message = f"draw failed: {exc}"

        for name, hz, fn in (("soma_view_step", self.rate_hz, self._step), ("soma_view_draw", self.draw_hz, draw)):
            t = threading.Thread(target=self._every, args=(hz, fn), name=name, daemon=True)
            t.start()
            self._threads.append(t)

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=5.0)
