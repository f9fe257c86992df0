"""A render's views: one camera from the options (a fog scene's viewpoint, or a volume file framed whole), made
into mono, stereo or N viewers, and the occluders' depth images."""

from __future__ import annotations

import argparse
import math

from volren.plan.options import DEFAULT_EYE, CliError
from volren.plan.volume import _volume_from_args


def framing_distance(corners, look_at, direction, up, fov_y: float, aspect: float, eye_offset: float = 0.0) -> float:
    """Distance from ``look_at`` along the unit ``direction`` (towards the eye) at which every corner lies inside the
    view: a corner at (x, y) across and z towards the eye needs D >= z + |x| / tan(fov_x / 2) and likewise in y;
    ``eye_offset`` widens x for eyes shifted sideways (stereo: ipd / 2). Ten percent of margin."""
    import numpy as np

    d = np.asarray(direction, dtype=float)
    right = np.cross(-d, up)
    if np.linalg.norm(right) < 1e-9:  # --up along the view: Camera refuses it next; any frame will do here
        right = np.cross(-d, np.eye(3)[np.argmin(np.abs(d))])
    right /= np.linalg.norm(right)
    true_up = np.cross(right, -d)
    rel = np.asarray(corners, dtype=float) - np.asarray(look_at, dtype=float)
    tan_y = math.tan(math.radians(fov_y) / 2)
    across = np.abs(rel @ right) + eye_offset
    need = rel @ d + np.maximum(across / (tan_y * aspect), np.abs(rel @ true_up) / tan_y)
    return 1.1 * float(need.max())


def views_from_args(args: argparse.Namespace, time: float = 0.0):
    """The viewers: one camera from the arguments (a fog scene's own viewpoint by default), made into mono, stereo
    or N views by ``--rig``; in a fog scene the arc and the wandering viewers keep to its walkable space (the arc
    only when the camera stands in it), elsewhere viewers wander 3 m around the look-at point; wandering viewers are
    placed for ``time`` [s]. A volume file is framed: the camera looks at its world box's centre from the default
    direction (0, 0.4, 3.2), far enough that the whole box is in view."""
    from volren.camera import Camera, make_views
    from volren.data.fog_scenes import FOG_SCENES, fog_scene_camera, fog_scene_walk_area
    from volren.viewers import WalkArea, arc_viewers, overlap_viewers, wandering_viewers

    position, look_at, near, ipd = DEFAULT_EYE, (0.0, 0.0, 0.0), 0.01, 0.063
    fog_scene = getattr(args, "scene", None) in FOG_SCENES
    if fog_scene:
        default = fog_scene_camera(args.scene)
        position, look_at = default["position"], default["look_at"]
    elif getattr(args, "volume", None) is not None and args.camera_pos is None:
        import numpy as np

        corners = _volume_from_args(args).corners_world
        look_at = tuple(args.look_at or (corners.min(axis=0) + corners.max(axis=0)) / 2)
        # eyes 63 mm apart would each see a 30 um stack as a speck off to the side
        ipd = min(ipd, float(np.ptp(corners, axis=0).max())) if args.ipd is None else args.ipd
        direction = np.array(position) / np.linalg.norm(position)
        distance = framing_distance(corners, look_at, direction, args.up, args.fov, args.width / max(args.height, 1),
                                    ipd / 2 if args.views == "stereo" else 0.0)
        position = tuple(np.array(look_at) + distance * direction)
        near = min(near, distance / 1000)  # a 100 um stack framed from 0.4 mm: the default 1 cm would clip it all
    cam = Camera(position=args.camera_pos or position, look_at=args.look_at or look_at, up=args.up, fov_y=args.fov,
                 width=args.width, height=args.height, near=near if args.near is None else args.near, far=args.far)
    if args.overlap is not None and args.rig != "overlap":
        raise CliError("--overlap needs --rig overlap and --views N")
    if args.views in ("mono", "stereo"):
        if args.rig is not None:
            raise CliError(f"--rig {args.rig} places N viewers, not --views {args.views}: give --views N")
        return make_views(cam, args.views, ipd if args.ipd is None else args.ipd)
    count = len(make_views(cam, args.views))  # validates N
    rig = args.rig or "arc"
    if rig == "overlap":
        return overlap_viewers(cam, count, 0.5 if args.overlap is None else args.overlap)
    area = fog_scene_walk_area(args.scene) if fog_scene else None
    if rig == "arc":
        return arc_viewers(cam, count, area)
    if area is None:
        x, y, z = cam.look_at
        area = WalkArea((x - 3.0, z - 3.0), (x + 3.0, z + 3.0), floor=y - 3.0)
    return wandering_viewers(cam, count, area, time=time, seed=args.seed)


def depth_images_from_args(args: argparse.Namespace, view_count: int) -> list | None:
    """``--depth-image``: one (H, W) image for every view, or a (views, H, W) stack."""
    if args.depth_image is None:
        return None
    import numpy as np

    try:
        depth = np.load(args.depth_image, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise CliError(f"cannot read depth image '{args.depth_image}': {exc}") from None
    if depth.ndim == 2:
        return [depth] * view_count
    if depth.ndim == 3 and depth.shape[0] == view_count:
        return list(depth)
    raise CliError(f"depth image must be (H, W) or ({view_count}, H, W), got shape {depth.shape}")
