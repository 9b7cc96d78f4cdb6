"""Episodes as training tensors: what the trainer and the evaluation read from a bag.

Shared API (stable; the evaluation code builds on it)::

    from soma_ros.data.dataset import load_dataset, prepare_episode
    refs = load_dataset("data/rope_tiny", "train")          # [EpisodeRef(name, bag, split, task, frames)]
    robot = RobotModel.from_config("panda", dtype=torch.float64)
    ep = prepare_episode(refs[0].bag, robot, data_cfg)       # EpisodeData
    cams = ep.cameras(t)                                     # Cameras: all C cameras at frame t
    action = ep.action(t)                                    # RobotAction in the sim frame
    pts, cols = ep.object_points([0])                        # fused masked depth of frame 0

Frames and units
----------------
The **simulation frame is the rig's world frame** (the frame the fixed
cameras hang off in /tf_static; ``TopicNames.world_frame``). Fixed cameras
come from /tf_static; a camera mounted on a robot link (the wrist camera)
moves with FK: ``T_world_cam(t) = T_world_base (tf_static) FK(q_t)[link]
T_link_cam (tf_static)``. The robot -> simulation similarity ``base_to_sim``
follows the paper's R2S mapping: the wrist camera's pose is known in the robot
frame (``FK(q_0)[link] T_link_cam``) and in the reconstruction frame (its
world pose), so ``base_to_sim = T_rec_cam T_rob_cam^-1`` (scale 1: the rig
is metric). With a calibrated rig, as here, this coincides with
``T_world_base`` from /tf_static; with a reconstruction frame from SfM one
passes the reconstruction-frame camera pose instead. Without a mounted camera
``T_world_base`` is used directly. All lengths in metres, time in seconds.

Tensor shapes of :class:`EpisodeData` (T frames, C cameras, H x W pixels at
the training resolution, P robot control points, J joints):

===================  ===================  ==============================================
field                shape / type         meaning
===================  ===================  ==============================================
stamps_ns            [T] int64            frame clock (first camera's colour stamps)
dt                   float                median frame interval, s
camera_names         list[str] (C)        sorted camera names
K                    [C, 3, 3] float64    intrinsics at the training resolution
cam_to_world         [T, C, 4, 4] f64     camera-to-sim poses (OpenCV optical frames)
rgb                  [T, C, H, W, 3] f32  in [0, 1]
depth                [T, C, H, W] f32     metres, 0 = invalid
object_mask          [T, C, H, W] bool    object pixels
robot_mask           [T, C, H, W] bool    robot pixels (all False if the bag has none)
loss_mask            [T, C, H, W] bool    object AND NOT robot: supervised pixels
joint_positions      [T, J] float64       joint state at the frame stamps
control_points       [T, P, 3] float32    robot control points, sim frame
gripper              [T] float32          gripper state c_t in [0, 1] (1 = open)
gripper_opening      [T] float32          jaw opening, m
ee_pose              [T, 4, 4] float64    end-effector pose in the sim frame
wrist_force          [T, 3] f64 or None   force on the end effector, N, sim frame, from the arm's
                                          external joint torques (/joint_states effort; None
                                          when the bag has no efforts or the arm < 6 joints)
===================  ===================  ==============================================

Training code reads bags only through :mod:`soma_ros.data.bags`, which never reads
the evaluation-only ``/world/object_points`` topic; nothing here reads the
``*.meta.json`` sidecars.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence, Union

import numpy as np
import torch

from soma_ros.core.calibration import Sim3, sim3_from_camera_poses
from soma_ros.core.cameras import Cameras, k_from_camera_info
from soma_ros.core.robot import RobotModel
from soma_ros.core.simulator import RobotAction

from soma_ros.data.bags import BagError, Episode, TopicConfig, camera_mount, read_episode, resolve_camera_poses, world_from_base
from soma_ros.data.config import DataConfig
from soma_ros.data.sources import ANY_SPLIT, MANIFEST, EpisodeRef, _read_manifest, load_dataset  # noqa: F401  (shared API)

__all__ = [
    "MANIFEST",
    "EpisodeRef",
    "EpisodeData",
    "load_manifest",
    "load_dataset",
    "prepare_episode",
    "topic_config",
    "backproject",
]


def load_manifest(dataset_dir: Union[str, Path]) -> dict:
    """``DATASET/manifest.json`` as a dict (FileNotFoundError / ValueError naming the problem)."""
    d = Path(dataset_dir)
    if not d.is_dir():
        raise FileNotFoundError(f"dataset folder not found: {d}")
    if not (d / MANIFEST).is_file():
        raise FileNotFoundError(f"dataset {d} has no {MANIFEST}")
    return _read_manifest(d)


def topic_config(cfg: DataConfig) -> TopicConfig:
    return cfg.topics  # TopicNames is a validated TopicConfig


# --------------------------------------------------------------------------- episode tensors
@dataclass
class EpisodeData:
    """One episode at the training resolution, in the simulation frame (module docstring)."""

    name: str
    path: Path
    stamps_ns: torch.Tensor
    dt: float
    camera_names: list[str]
    width: int
    height: int
    K: torch.Tensor
    cam_to_world: torch.Tensor
    rgb: torch.Tensor
    depth: torch.Tensor
    object_mask: torch.Tensor
    robot_mask: torch.Tensor
    loss_mask: torch.Tensor
    joint_names: list[str]
    joint_positions: torch.Tensor
    control_points: torch.Tensor
    gripper: torch.Tensor
    gripper_opening: torch.Tensor
    ee_pose: torch.Tensor
    base_to_sim: Sim3
    mounts: dict[str, tuple[str, np.ndarray]] = field(default_factory=dict)
    world_frame: str = "world"
    wrist_force: Optional[torch.Tensor] = None
    #: per camera, where its masks came from: "bag", "folder" or "derived"
    mask_source: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        T, C, H, W = self.num_frames, len(self.camera_names), self.height, self.width
        P = self.control_points.shape[1]
        expect = {
            "stamps_ns": (T,), "K": (C, 3, 3), "cam_to_world": (T, C, 4, 4), "rgb": (T, C, H, W, 3),
            "depth": (T, C, H, W), "object_mask": (T, C, H, W), "robot_mask": (T, C, H, W),
            "loss_mask": (T, C, H, W), "control_points": (T, P, 3), "gripper": (T,), "gripper_opening": (T,),
            "ee_pose": (T, 4, 4),
        }
        for name, shape in expect.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise ValueError(f"EpisodeData {self.name}: {name} must be {list(shape)}, got {list(got)}")
        if self.joint_positions.shape != (T, len(self.joint_names)):
            raise ValueError(f"EpisodeData {self.name}: joint_positions must be [T, J]")
        if self.wrist_force is not None and tuple(self.wrist_force.shape) != (T, 3):
            raise ValueError(f"EpisodeData {self.name}: wrist_force must be [T, 3], got {list(self.wrist_force.shape)}")

    # ------------------------------------------------------------------ sizes
    @property
    def num_frames(self) -> int:
        return int(self.stamps_ns.shape[0])

    @property
    def num_cameras(self) -> int:
        return len(self.camera_names)

    # ------------------------------------------------------------------ accessors
    def cameras(self, t: int, dtype: torch.dtype = torch.float32, device=None,
                select: Optional[Sequence[int]] = None) -> Cameras:
        """The C cameras (or ``select``) at frame t, at the training resolution."""
        idx = list(range(self.num_cameras)) if select is None else list(select)
        return Cameras.from_cam_to_world(self.K[idx], self.cam_to_world[t, idx], self.width, self.height,
                                         [self.camera_names[i] for i in idx], dtype=dtype, device=device)

    def action(self, t: int, dtype: torch.dtype = torch.float32, device=None) -> RobotAction:
        """The robot action R_t in the sim frame: control points [P, 3] and gripper c_t."""
        return RobotAction(self.control_points[t].to(device=device, dtype=dtype),
                           self.gripper[t].to(device=device, dtype=dtype))

    def actions(self, frames: Sequence[int], dtype: torch.dtype = torch.float32, device=None) -> list[RobotAction]:
        return [self.action(int(t), dtype, device) for t in frames]

    def camera_index(self, name: str) -> int:
        if name not in self.camera_names:
            raise ValueError(f"episode {self.name} has no camera '{name}' (have {', '.join(self.camera_names)})")
        return self.camera_names.index(name)

    def object_points(self, frames: Sequence[int] = (0,), erode_px: int = 0,
                      cameras: Optional[Sequence[str]] = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Fused object points of the given frames: every camera's pixels with
        ``object & ~robot & depth > 0`` (masks eroded by ``erode_px``) back-projected into
        the sim frame. Returns (points [N, 3] float32, colours [N, 3] float32 in [0, 1])."""
        pts, cols = [], []
        cams = range(self.num_cameras) if cameras is None else [self.camera_index(c) for c in cameras]
        for t in frames:
            if not 0 <= t < self.num_frames:
                raise ValueError(f"episode {self.name}: frame {t} out of range [0, {self.num_frames})")
            for c in cams:
                m = self.loss_mask[t, c] & (self.depth[t, c] > 0)
                if erode_px > 0:
                    m = _erode(m, erode_px)
                p, col = backproject(self.depth[t, c], self.K[c], self.cam_to_world[t, c], m, self.rgb[t, c])
                pts.append(p)
                cols.append(col)
        P = torch.cat(pts) if pts else torch.zeros(0, 3)
        Cl = torch.cat(cols) if cols else torch.zeros(0, 3)
        return P.float(), Cl.float()

    def background_points(self, t: int = 0, cameras: Optional[Sequence[str]] = None) -> torch.Tensor:
        """Sim-frame points [N, 3] of pixels that are neither object nor robot (table, floor...)."""
        pts = []
        cams = range(self.num_cameras) if cameras is None else [self.camera_index(c) for c in cameras]
        for c in cams:
            m = ~self.object_mask[t, c] & ~self.robot_mask[t, c] & (self.depth[t, c] > 0)
            p, _ = backproject(self.depth[t, c], self.K[c], self.cam_to_world[t, c], m)
            pts.append(p)
        return torch.cat(pts).float() if pts else torch.zeros(0, 3)

    def mounted_camera(self) -> Optional[str]:
        """Name of the first camera mounted on a robot link (the wrist camera), else None."""
        for c in self.camera_names:
            if self.mounts.get(c, (self.world_frame,))[0] != self.world_frame:
                return c
        return None


def backproject(depth: torch.Tensor, K: torch.Tensor, cam_to_world: torch.Tensor, mask: torch.Tensor,
                rgb: Optional[torch.Tensor] = None) -> tuple[torch.Tensor, Optional[torch.Tensor]]:
    """Pixels of ``mask`` [H, W] with depth [H, W] (m, camera z) -> world points [N, 3] float64
    (pixel centres at +0.5, OpenCV optical frame) and their colours [N, 3] from ``rgb`` [H, W, 3]."""
    v, u = torch.nonzero(mask, as_tuple=True)
    z = depth[v, u].double()
    K = K.double()
    x = (u.double() + 0.5 - K[0, 2]) / K[0, 0] * z
    y = (v.double() + 0.5 - K[1, 2]) / K[1, 1] * z
    pc = torch.stack([x, y, z], dim=-1)
    T = cam_to_world.double()
    pw = pc @ T[:3, :3].T + T[:3, 3]
    col = rgb[v, u] if rgb is not None else None
    return pw, col


def _erode(mask: torch.Tensor, px: int) -> torch.Tensor:
    k = 2 * px + 1
    m = (~mask)[None, None].float()
    return ~(torch.nn.functional.max_pool2d(m, k, stride=1, padding=px)[0, 0] > 0)


def _resize_stack(arr: np.ndarray, w: int, h: int, kind: str) -> np.ndarray:
    """Resize [T, H, W(, 3)]: 'area' for colour, 'nearest' for depth, 'mask' (area > 0.5) for masks."""
    import cv2

    if arr.shape[2] == w and arr.shape[1] == h:
        return arr
    out = []
    for a in arr:
        if kind == "area":
            out.append(cv2.resize(a, (w, h), interpolation=cv2.INTER_AREA))
        elif kind == "nearest":
            out.append(cv2.resize(a, (w, h), interpolation=cv2.INTER_NEAREST))
        else:
            out.append(cv2.resize(a.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA) >= 0.5)
    return np.stack(out)


def episode_masks(ep: Episode, robot: RobotModel, fk_np: dict[str, np.ndarray], cfg: DataConfig, name: str,
                  mask_cache: Optional[Path] = None) -> dict[str, str]:
    """Fill every camera's missing ``object_mask`` / ``robot_mask`` [T, H, W] of ``ep`` (poses resolved)
    by ``cfg.masks`` (:mod:`soma_ros.data.masks`): the bag's topics, a PNG folder, or derived from geometry
    (cached in ``mask_cache`` when given). Returns {camera: "bag" | "folder" | "derived"}."""
    from soma_ros.data.masks import cache_key, derive_masks, load_mask_folder

    mc = cfg.masks
    src: dict[str, str] = {}
    T = ep.num_frames
    for c, s in ep.cameras.items():
        if mc.source == "derive":
            s.object_mask = s.robot_mask = None
        if s.object_mask is not None:
            src[c] = "bag"
            continue
        if mc.source == "bag":
            raise BagError(f"{ep.path.name}: missing topic {cfg.topics.topic('object_mask', s.topics.namespace if s.topics else c)} "
                           "(data.masks.source: bag)")
        if mc.folder and mc.source in ("auto", "folder"):
            om = load_mask_folder(Path(mc.folder), name, c, T, s.height, s.width, "object")
            if om is not None:
                s.object_mask = om
                rm = load_mask_folder(Path(mc.folder), name, c, T, s.height, s.width, "robot")
                if rm is not None:
                    s.robot_mask = rm
                src[c] = "folder"
                continue
            if mc.source == "folder":
                raise BagError(f"{Path(mc.folder) / name / c}: no object_<frame>.png masks for camera '{c}'")
    todo = [c for c in ep.cameras if c not in src or ep.cameras[c].robot_mask is None]
    if not todo:
        return src
    key = cache_key(ep.path, mc, todo, T, f"{robot.config.urdf}:{cfg.topics.world_frame}")
    cached = None if mask_cache is None else Path(mask_cache) / f"{ep.path.name}-{key}.npz"
    if cached is not None and cached.is_file():
        z = np.load(cached)
        obj = {c: z[f"object/{c}"] for c in todo}
        rob = {c: z[f"robot/{c}"] for c in todo}
    else:
        from soma_ros.core.robot_meshes import load_link_meshes

        T_wb = world_from_base(ep, robot.base_link, cfg.topics.world_frame)
        links = {k: T_wb[None] @ v for k, v in fk_np.items()}
        try:
            meshes = load_link_meshes(robot.config.urdf, mc.robot_geometry)
        except FileNotFoundError as exc:
            raise FileNotFoundError(f"{exc}; robot pixels are found from the URDF's meshes: install them where the "
                                    "URDF points, or give the masks (mask topics in the bags, or data.masks.folder)") from None
        dm = derive_masks(ep, links, meshes, mc, cameras=todo)
        obj, rob = dm.object_mask, dm.robot_mask
        if cached is not None:
            cached.parent.mkdir(parents=True, exist_ok=True)
            tmp = cached.with_name(cached.stem + ".tmp.npz")
            np.savez_compressed(tmp, **{f"object/{c}": obj[c] for c in todo}, **{f"robot/{c}": rob[c] for c in todo})
            tmp.replace(cached)
    for c in todo:
        s = ep.cameras[c]
        if c not in src:
            s.object_mask = obj[c]
            src[c] = "derived"
        if s.robot_mask is None:
            s.robot_mask = rob[c]
    return src


def prepare_episode(
    bag: Union[str, Path],
    robot: RobotModel,
    cfg: Optional[DataConfig] = None,
    base_to_sim: Optional[Sim3] = None,
    name: Optional[str] = None,
    mask_cache: Optional[Path] = None,
) -> EpisodeData:
    """Read one bag into :class:`EpisodeData` (see module docstring).

    ``robot``: the rig's robot (float64 recommended). ``cfg``: data section (or a whole
    TrainConfig); defaults if None. ``base_to_sim``: force this robot -> sim similarity
    (e.g. a scene bundle's), else it is computed from the wrist camera as the paper does.
    Masks a bag lacks come from ``cfg.masks`` (:func:`episode_masks`; derived ones are cached
    in ``mask_cache`` when given). Raises :class:`~soma_ros.data.bags.BagError` (one line) for unusable bags.
    """
    if hasattr(cfg, "data") and not isinstance(cfg, DataConfig):  # a whole training config
        cfg = cfg.data
    cfg = cfg or DataConfig()
    bag = Path(bag)
    topics = topic_config(cfg)
    ep: Episode = read_episode(bag, cameras=cfg.cameras, topics=topics, sync_tolerance_ms=cfg.sync_tolerance_ms,
                               require_masks=cfg.require_masks or cfg.masks.source == "bag", max_frames=cfg.max_frames)
    T = ep.num_frames
    if T < 2:
        raise BagError(f"{bag.name}: only {T} synchronised frame(s); need at least 2")
    wf = topics.world_frame
    try:
        q = robot.q_from_joint_state(ep.joint_names, ep.joint_positions)  # [T, n]
        opening, grip = robot.gripper_state(ep.joint_names, ep.joint_positions)  # [T], [T]
    except ValueError as exc:
        raise BagError(f"{bag.name}: {topics.joint_states}: {exc}") from None
    fk = robot.fk(q)
    fk_np = {k: v.detach().cpu().double().numpy() for k, v in fk.items()}
    resolve_camera_poses(ep, lambda names, pos: fk_np, robot.base_link, wf, robot.link_names)
    mounts = {c: camera_mount(ep, c, wf, robot.link_names) for c in ep.cameras}
    mask_source = episode_masks(ep, robot, fk_np, cfg, name or bag.name, mask_cache)

    # robot -> sim similarity (paper appendix "Transformation of Robot Conditioning")
    if base_to_sim is None:
        wrist = next((c for c in sorted(ep.cameras) if mounts[c][0] != wf), None)
        if wrist is not None:
            link, T_link_cam = mounts[wrist]
            T_rob_cam = fk_np[link][0] @ T_link_cam  # camera in the robot base frame (URDF FK + mount)
            T_rec_cam = ep.cameras[wrist].cam_to_world[0]  # the same camera in the reconstruction (= world) frame
            base_to_sim = sim3_from_camera_poses(T_rob_cam, T_rec_cam, scale=1.0)
        else:
            base_to_sim = Sim3.from_matrix(world_from_base(ep, robot.base_link, wf))

    # the force on the hand from the arm's external joint torques, rotated into the sim frame
    wrist_force = None
    if ep.joint_efforts is not None and len(robot.arm_joint_names) >= 6:
        try:
            w = robot.external_wrench(ep.joint_names, ep.joint_positions, ep.joint_efforts).double()
        except ValueError as exc:
            raise BagError(f"{bag.name}: {topics.joint_states} efforts: {exc}") from None
        wrist_force = torch.from_numpy(w[:, :3].numpy() @ base_to_sim.R.T)  # [T, 3] N

    cps = robot.control_points(q, opening.to(q.dtype))  # [T, P, 3] base frame
    cps_sim = base_to_sim.apply_points(cps.double())
    ee = base_to_sim.apply_pose(fk[robot.ee_link].double())

    names = sorted(ep.cameras)
    streams = [ep.cameras[c] for c in names]
    H0, W0 = streams[0].height, streams[0].width
    for s in streams[1:]:
        if (s.height, s.width) != (H0, W0):
            raise BagError(f"{bag.name}: camera '{s.name}' is {s.width}x{s.height}, '{streams[0].name}' {W0}x{H0}; "
                           "all cameras must share one image size")
    sc = cfg.resolution_scale
    W, H = max(1, int(round(W0 * sc))), max(1, int(round(H0 * sc)))
    Ks = []
    rgb, depth, om, rm = [], [], [], []
    for s in streams:
        Ks.append(k_from_camera_info(s.K, W / W0, H / H0))  # CameraInfo -> the renderer's pixel centres
        rgb.append(_resize_stack(s.rgb, W, H, "area"))
        depth.append(_resize_stack(s.depth, W, H, "nearest"))
        o = s.object_mask if s.object_mask is not None else np.zeros((T, H0, W0), bool)
        r = s.robot_mask if s.robot_mask is not None else np.zeros((T, H0, W0), bool)
        om.append(_resize_stack(o, W, H, "mask"))
        rm.append(_resize_stack(r, W, H, "mask"))
    rgb_t = torch.from_numpy(np.stack(rgb, axis=1)).float().div_(255.0)  # [T, C, H, W, 3]
    depth_t = torch.from_numpy(np.stack(depth, axis=1).astype(np.float32))
    om_t = torch.from_numpy(np.stack(om, axis=1))
    rm_t = torch.from_numpy(np.stack(rm, axis=1))
    c2w = torch.from_numpy(np.stack([s.cam_to_world for s in streams], axis=1))  # [T, C, 4, 4]
    stamps = torch.from_numpy(ep.stamps_ns.astype(np.int64))
    dt = float(np.median(np.diff(ep.stamps_ns))) / 1e9
    if not dt > 0:
        raise BagError(f"{bag.name}: frame stamps do not increase")
    return EpisodeData(
        name=name or bag.name, path=bag, stamps_ns=stamps, dt=dt, camera_names=names, width=W, height=H,
        K=torch.from_numpy(np.stack(Ks)), cam_to_world=c2w, rgb=rgb_t, depth=depth_t, object_mask=om_t,
        robot_mask=rm_t, loss_mask=om_t & ~rm_t, joint_names=list(ep.joint_names),
        joint_positions=torch.from_numpy(ep.joint_positions), control_points=cps_sim.float(),
        gripper=grip.float(), gripper_opening=opening.float(), ee_pose=ee, base_to_sim=base_to_sim,
        mounts=mounts, world_frame=wf, wrist_force=wrist_force, mask_source=mask_source,
    )
