"""occvo run: odometry and mapping over a scene, writing trajectory, map, plot and summary."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from occvo_cli.commands.make_occupancy import index_range
from occvo_cli.outputs import add_output_flags
from occvo_cli.paths import out_dir
from occvo_core import OccVOConfig


def add_parser(sub) -> None:
    p = sub.add_parser("run", help="run OCC-VO over a scene (a synthetic one when no --input is given)")
    p.add_argument(
        "--input",
        type=Path,
        help="scene folder: OCC-VO release occupancy/<scene>/, Occ3D scene folder, a nuScenes drive (devkit layout), "
        "or a ROS 2 recording of occupancy clouds (FILE.mcap or a bag folder)",
    )
    p.add_argument(
        "--occupancy-topic", help="a recording's occupancy clouds (sensor_msgs/PointCloud2; default /occvo/occupancy)"
    )
    p.add_argument(
        "--image-topic",
        help="--from-images on a recording: the cameras' CompressedImage topics, {camera} for CAM_FRONT etc. "
        "(default /{camera}/image_rect_compressed)",
    )
    p.add_argument(
        "--camera-info-topic", help="--from-images on a recording: their CameraInfo (default /{camera}/camera_info)"
    )
    p.add_argument(
        "--groundtruth-topic",
        help="a recording's ground truth (PoseStamped or Odometry at each cloud's stamp; default /occvo/groundtruth)",
    )
    p.add_argument("--scene", help="with an Occ3D-nuScenes root or a nuScenes drive as --input: the scene to run")
    p.add_argument(
        "--occupancy",
        choices=("lidar",),
        help="a nuScenes drive's occupancy made from each keyframe's own LiDAR sweep (or --from-images: the cameras)",
    )
    p.add_argument(
        "--keyframes",
        type=index_range,
        metavar="A-B",
        help="a nuScenes drive's keyframes A-B only: the run starts at keyframe A as its frame 0",
    )
    p.add_argument(
        "--list-scenes", action="store_true", help="list the scenes of the Occ3D-nuScenes root --input and exit"
    )
    p.add_argument(
        "--mask",
        choices=("camera", "lidar", "none"),
        default="camera",
        help="the visibility mask whose voxels make a frame (default: camera): of Occ3D input, or with --from-images "
        "of the network's prediction (camera or none)",
    )
    p.add_argument("--gt", type=Path, help="ground-truth trajectory (KITTI or TUM) for APE")
    p.add_argument(
        "--start-time",
        type=float,
        metavar="UNIX_SECONDS",
        help="stamp the frames of an --input scene whose data has no stamps (the OCC-VO release) from this time on, "
        "at the frame rate (default: from 0, 1970-01-01, with a warning)",
    )
    p.add_argument("--out", type=out_dir, default="occvo-out", help="output folder (default: occvo-out)")
    p.add_argument("--config", type=Path, help="OccVOConfig as JSON/JSON5")
    p.add_argument("--no-semantic-filter", action="store_true", help="switch the semantic label filter off")
    p.add_argument("--no-dynamic-filter", action="store_true", help="switch the dynamic object filter off")
    p.add_argument("--no-pfilter", action="store_true", help="switch the voxel pfilter off")
    p.add_argument(
        "--threads",
        type=int,
        default=0,
        help="cores the registration kernels may use (default 0: those other processes leave free), and with "
        "--from-images torch's threads too; registration's result does not depend on it, the network's last bits do",
    )
    p.add_argument(
        "--skip-bad-frames", action="store_true", help="skip frames that fail validation instead of stopping"
    )
    p.add_argument("--seed", type=int, default=0, help="synthetic scene seed (no --input)")
    p.add_argument(
        "--frames",
        type=int,
        help="frames to run: the first N of --input (default: all), or the synthetic scene's length (default: 40)",
    )
    p.add_argument("--rate", type=float, default=2.0, help="synthetic frame rate in Hz (no --input)")
    p.add_argument("--noise", default="default", help="synthetic prediction noise preset: none, default, heavy")
    p.add_argument("--synthetic", action="store_true", help="a synthetic scene (the default when no --input is given)")
    p.add_argument(
        "--from-images",
        action="store_true",
        help="occupancy predicted by --checkpoint from the six cameras: a nuScenes drive's real images, or the "
        "synthetic scene's rendered ones",
    )
    p.add_argument(
        "--checkpoint",
        type=Path,
        help="TPV-Former checkpoint for --from-images (default: the shipped one, for a nuScenes drive the one "
        "trained on real images, for the synthetic town tiny)",
    )
    p.add_argument(
        "--min-confidence",
        type=float,
        help="--from-images: voxels the network is less sure of than this (softmax of its class) are free "
        "(default: the shipped model's own, 0 with --checkpoint)",
    )
    p.add_argument(
        "--min-ground-confidence",
        type=float,
        help="--from-images: the same for the ground classes, 1: no ground voxel at all "
        "(default: the shipped model's own, 0 with --checkpoint)",
    )
    p.add_argument(
        "--motion-search",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="refine each frame's constant-velocity guess by the semantic BEV motion search "
        "(initialisation.motion_search; default: on with --from-images, else as the config says)",
    )
    add_output_flags(p)
    p.add_argument("--json", action="store_true", help="the summary as JSON on stdout")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def config_from_args(args, source=None) -> OccVOConfig:
    defaults = getattr(source, "config_defaults", None)  # a source's own (LiDAR occupancy), under --config
    cfg = OccVOConfig.load(args.config, defaults) if args.config else OccVOConfig.model_validate(defaults or {})
    search = getattr(args, "motion_search", None)
    if search is None and getattr(args, "from_images", False):
        search = True  # camera occupancy needs it to follow turns; it costs time every frame
    if search is not None:
        cfg = cfg.with_motion_search(search)
    return cfg.with_filters(
        semantic=cfg.semantic_label_filter.enabled and not args.no_semantic_filter,
        dynamic=cfg.dynamic_object_filter.enabled and not args.no_dynamic_filter,
        pfilter=cfg.voxel_pfilter.enabled and not args.no_pfilter,
    )


def run(args) -> int:
    from occvo_cli.outputs import check_outputs, open_outputs
    from occvo_cli.run_record import write_run_record
    from occvo_core.datasets import open_scene
    from occvo_core.errors import ConfigError
    from occvo_core.pipeline import OdometryPipeline

    if args.list_scenes:
        return _list_scenes(args.input)
    check_outputs(args)
    if args.input is not None and args.synthetic:
        raise ConfigError("--input reads a recorded scene; --synthetic makes one: give one or the other")
    if args.from_images and args.occupancy:
        raise ConfigError("--from-images and --occupancy lidar are two ways to make occupancy: choose one")
    if args.input is None and args.gt is not None:
        raise ConfigError("--gt is the ground truth of an --input scene; a synthetic scene brings its own")
    if args.input is None and args.start_time is not None:
        raise ConfigError("--start-time stamps an --input scene without stamps; a synthetic scene has its own clock")
    truth = None
    if args.from_images:
        source = _image_source(args)
        truth = source.scene if args.input is None else None  # the synthetic town's true occupancy scores the map
    elif args.input is None:
        from occvo_core.sim import SyntheticScene

        source = truth = SyntheticScene(seed=args.seed, frames=_length(args), rate_hz=args.rate, noise=args.noise)
    else:
        topics = {"topic": args.occupancy_topic, "gt_topic": args.groundtruth_topic}
        source = open_scene(
            args.input, gt=args.gt, scene=args.scene, mask=args.mask, occupancy=args.occupancy, topics=topics
        )
    if args.keyframes is not None:
        from occvo_core.datasets.frame_range import FrameRange
        from occvo_core.datasets.nuscenes_tables import is_nuscenes_root

        if args.input is None or not is_nuscenes_root(args.input):
            raise ConfigError("--keyframes picks keyframes of a nuScenes drive: give --input DRIVE")
        source = FrameRange(source, *args.keyframes)
    if args.input is not None:
        _stamp(source, args)
        source = _first_frames(source, args.frames)
    config = config_from_args(args, source)
    extra = {"compile_s": _warm_up(config, args)}
    view = open_outputs(args)
    try:
        pipeline = OdometryPipeline(
            source, config, skip_bad_frames=args.skip_bad_frames, threads=args.threads, progress=not args.quiet
        ).run(on_step=view.step if view else None)
        if view:
            view.finish(pipeline.odometry)
    except BaseException:
        if view:
            view.abandon()  # no half-written recording
        raise
    if truth is not None:
        extra["map_metrics"] = _synthetic_map_metrics(truth, pipeline)
    if args.from_images:
        import torch

        extra["torch_threads"], extra["camera_mask"] = torch.get_num_threads(), source.predictor.camera_mask
    summary = pipeline.write(args.out, extra)
    write_run_record(args.out, args, config, source)
    shown = {k: summary[k] for k in summary if k not in ("skipped_frames",)}
    if args.json:
        print(json.dumps({**shown, "out": str(args.out)}, indent=2, default=float))
    else:
        print(_text(shown, args.out))
    if summary.get("success") is False:  # the run's own rule (occvo_core.eval.success) says it failed
        print(
            f"occvo run: error: the run failed its success rule: APE RMSE {summary['ape_rmse_m']:.2f} m "
            f"(summary in {args.out}/summary.json)",
            file=sys.stderr,
        )
        return 1
    return 0


def _image_source(args):
    """The six cameras through TPV-Former: a nuScenes drive's real images, or the synthetic scene rendered."""
    from occvo_core.errors import ConfigError
    from occvo_core.models.tpvformer.checkpoint import served_model
    from occvo_core.models.tpvformer.predictor import OccupancyPredictor

    if args.mask == "lidar":
        raise ConfigError("--mask lidar: a camera model's prediction has no lidar; give camera or none")
    given = (args.min_confidence, args.min_ground_confidence)
    if args.checkpoint:
        checkpoint, served = args.checkpoint, (0.0, 0.0)
    else:  # a real drive: the model that saw real images
        checkpoint, served = served_model(real_rig=args.input is not None)
    min_conf, min_ground = (s if g is None else g for g, s in zip(given, served))
    predictor = OccupancyPredictor(
        checkpoint,
        min_confidence=min_conf,
        min_ground_confidence=min_ground,
        camera_mask=args.mask == "camera",
    )
    import torch

    if args.threads:  # torch's sums split by thread count: one count, the same voxels on any machine
        torch.set_num_threads(args.threads)
    if args.input is not None:
        from occvo_core.datasets.nuscenes_drive import NuScenesDrive
        from occvo_core.datasets.nuscenes_tables import is_nuscenes_root
        from occvo_core.datasets.ros2_recording import is_recording
        from occvo_core.models.image_source import NuScenesImageSource

        if is_recording(args.input):  # six cameras as nuscenes2mcap records them, in place of a drive's files
            from occvo_core.datasets.ros2_cameras import IMAGE_TOPIC, INFO_TOPIC, RecordedCameras

            cameras = RecordedCameras(args.input, args.image_topic or IMAGE_TOPIC, args.camera_info_topic or INFO_TOPIC)
            return NuScenesImageSource(cameras, predictor)
        if not is_nuscenes_root(args.input):
            raise ConfigError(
                f"--from-images reads a nuScenes drive's cameras or a ROS 2 recording's; {args.input} is neither"
            )
        return NuScenesImageSource(NuScenesDrive(args.input, scene=args.scene), predictor)
    from occvo_core.models.image_source import ImageOccupancySource
    from occvo_core.sim import SyntheticScene

    scene = SyntheticScene(seed=args.seed, frames=_length(args), rate_hz=args.rate, noise=args.noise)
    return ImageOccupancySource(scene, predictor)


def _first_frames(source, frames: int | None):
    from occvo_core.datasets.base import FirstFrames
    from occvo_core.errors import ConfigError

    if frames is None:
        return source
    if frames < 1:
        raise ConfigError(f"--frames must be a positive integer, got {frames}")
    return FirstFrames(source, frames)


def _length(args) -> int:
    """A synthetic scene's frames: --frames, 40 by default (with --input, --frames takes the first N)."""
    return 40 if args.frames is None else args.frames


def _stamp(source, args) -> None:
    """Frames whose data has no stamps (the OCC-VO release) are index / rate seconds: from --start-time on, else
    from 1970, said once on stderr."""
    import math

    import numpy as np

    from occvo_core.errors import ConfigError

    if not hasattr(source, "stamps") or source.stamps is not None:  # the data's own stamps
        if args.start_time is not None:
            raise ConfigError(f"--start-time: {source.name} has its own stamps (the data's); leave --start-time out")
        return
    if args.start_time is None:
        if not args.quiet:
            print(
                f"occvo run: warning: {source.name} has no stamps: its frames are stamped from 0 (1970-01-01) at "
                f"{source.rate_hz:g} Hz; --start-time UNIX_SECONDS stamps them from then",
                file=sys.stderr,
            )
        return
    if not math.isfinite(args.start_time):
        raise ConfigError(f"--start-time must be a finite number of seconds, got {args.start_time}")
    source.stamps = args.start_time + np.arange(len(source)) / source.rate_hz


def _list_scenes(root) -> int:
    from occvo_core.datasets.occ3d_nuscenes import list_scenes, release_root
    from occvo_core.errors import ConfigError

    if root is None or release_root(root) != root:
        raise ConfigError("--list-scenes needs --input OCC3D_ROOT (the folder holding annotations.json and gts/)")
    for s in list_scenes(root):
        print(json.dumps(s))
    return 0


def _text(s: dict, out: Path) -> str:
    lines = [f"scene {s['scene']}: {s['frames']} frames registered"]
    if "ape_rmse_m" in s:
        lines.append(f"APE RMSE {s['ape_rmse_m']:.3f} m ({'success' if s['success'] else 'FAILED'})")
    if s.get("ms_per_frame_median") is not None:
        ms, warm = s["ms_per_frame_median"], s.get("compile_s", 0.0)
        lines.append(f"{ms:.1f} ms a frame (median); kernel warm-up before the frames {warm:.1f} s")
    lines.append(f"map: {s['map_voxels']} voxels (the voxel pfilter's persistent ones of {s['live_voxels']} live)")
    truth = " groundtruth.kitti groundtruth.tum" if "ape_rmse_m" in s else ""
    lines.append(
        f"wrote {out}/: trajectory.kitti trajectory.tum{truth} map.ply map.npz map_voxels.npz trajectory.png "
        "summary.json run.json"
    )
    return "\n".join(lines)


def _warm_up(config: OccVOConfig, args) -> float:
    """Every registration kernel compiled (a first run after install) or loaded from numba's cache before the frames
    are timed, so ms_per_frame_median is a frame's cost and the compile time is reported apart, as compile_s."""
    from occvo_core.warm_up import warm_up

    if not args.quiet:
        # one write, line end included: a Ctrl-C between text and newline would put the next line on this one
        sys.stderr.write("occvo run: loading the registration kernels (a first run compiles them, ~40 s on 2 cores)\n")
        sys.stderr.flush()
    return float(warm_up(config, threads=args.threads)["seconds"])


def _synthetic_map_metrics(source, pipeline) -> dict:
    from occvo_core.map_metrics import evaluate_map_against_truth

    return evaluate_map_against_truth(source, pipeline.odometry)
