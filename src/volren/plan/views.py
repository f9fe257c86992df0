"""A render's views: one camera from the options (a fog scene's viewpoint, a volume file framed whole, a built-in
volume scene framed by its content), made into mono, stereo or N viewers, and the occluders' depth images."""

from __future__ import annotations

import argparse

from volren.framing import DEFAULT_FAR, framed_content, framed_eye, framing_distance
from volren.plan.options import DEFAULT_EYE, CliError
from volren.plan.volume import _volume_from_args

__all__ = ["depth_images_from_args", "framed_ipd", "framing_distance", "views_from_args"]


def views_from_args(args: argparse.Namespace, time: float = 0.0, scene=None):
    """The viewers: one camera from the arguments (a fog scene's own viewpoint by default), made into mono, stereo
    or N views by ``--rig``; in a fog scene the arc and the wandering viewers keep to its walkable space (the arc
    only when the camera stands in it), elsewhere viewers wander 3 m around the look-at point; wandering viewers are
    placed for ``time`` [s]. A volume file is framed: the camera looks at its world box's centre from the default
    direction (0, 0.4, 3.2), far enough that the whole box is in view. A built-in volume scene (``scene``, the
    planned one; built here when None) without --camera-pos and --look-at is framed by its content, both eyes of a
    stereo pair (`volren.framing.framed_content`)."""
    from volren.camera import Camera, make_views
    from volren.data.fog_scenes import FOG_SCENES, fog_scene_camera, fog_scene_walk_area
    from volren.viewers import WalkArea, arc_viewers, overlap_viewers, wandering_viewers

    if not 0 < args.fov < 180:  # refused before framing divides by tan(fov / 2)
        raise CliError(f"--fov must lie in (0, 180) degrees, got {args.fov:g}")
    position, look_at, near, far, ipd = DEFAULT_EYE, (0.0, 0.0, 0.0), 0.01, DEFAULT_FAR, 0.063
    fog_scene = getattr(args, "scene", None) in FOG_SCENES
    if fog_scene:
        default = fog_scene_camera(args.scene)
        position, look_at = default["position"], default["look_at"]
    elif getattr(args, "volume", None) is not None and args.camera_pos is None:
        corners = _volume_from_args(args).corners_world
        ipd = framed_ipd(corners) if args.ipd is None else args.ipd
        position, look_at, near, far = framed_eye(corners, args.up, args.fov, args.width / max(args.height, 1),
                                                  args.look_at, ipd / 2 if args.views == "stereo" else 0.0)
    elif args.camera_pos is None and args.look_at is None:  # a built-in volume scene
        if scene is None:
            from volren.plan.scene import scene_from_args

            scene = scene_from_args(args, time)
        eye_offset = (ipd if args.ipd is None else args.ipd) / 2 if args.views == "stereo" else 0.0
        position, look_at, near, far = framed_content(scene.volumes, args.up, args.fov,
                                                      args.width / max(args.height, 1), eye_offset)
    cam = Camera(position=args.camera_pos or position, look_at=args.look_at or look_at, up=args.up, fov_y=args.fov,
                 width=args.width, height=args.height, near=near if args.near is None else args.near,
                 far=far if args.far is None else args.far)
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


def framed_ipd(corners, ipd: float = 0.063) -> float:
    """[m] the eye distance of a framed volume's stereo pair: ``ipd``, at most its box's longest extent (eyes 63 mm
    apart would each see a 30 um stack as a speck off to the side)."""
    import numpy as np

    return min(ipd, float(np.ptp(np.asarray(corners), axis=0).max()))


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
