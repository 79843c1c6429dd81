"""playback stage: the twin in motion — the splats move with the simulated objects, the robot is in the
picture, any camera (capture, user, eye-in-hand) renders the scene as it changes.

Layering: capture -> poses -> splat -> semantics -> geometry -> twin -> robot -> **playback** -> report/viewer.
It may import anything below it; only report, viewer and the CLI import it.

`view_model.TwinView`: the twin as the viewer and the report draw it (splat layers, label colours,
collision parts, the robot's recorded track), without any GUI.

Entry points (thin calls for the report, the viewer and `plan --record`):
    scene = DynamicScene.load(twin_dir)                       # splats split into background + objects, holes
    renderer = PlaybackRenderer(scene, RobotSplats.panda())   # robot as Gaussians (compositor.py; robot.py says why)
    frame = renderer.render(camera, object_poses, RobotPose(q_arm, gripper_width))   # one photoreal frame
                                                              # (rgb, depth, alpha); RobotPose: playback.robot
    render_rollout_video(renderer, rollout, camera, out_mp4)  # MP4 of an executed task (playback.movie)
    write_episode(out_dir, rollout, renderer, cameras)        # LeRobot-layout episode (playback.episode)
    read_episode(dataset_dir, index)                          # ... and back
CLI: `splattwin render TWIN --camera CAM --out video.mp4`.
"""

from __future__ import annotations

from splattwin._lazy import lazy_exports

# Lazy: nothing is imported until a name is used (`splattwin --help` imports the options modules only).
_EXPORTS = {"DynamicScene": "scene", "PlaybackRenderer": "compositor", "RobotSplats": "robot", "render_rollout_video": "movie",
            "write_episode": "episode", "read_episode": "episode", "TwinView": "view_model", "RefineOptions": "options"}

__all__ = list(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
