"""robot stage: the Franka Panda (MuJoCo Menagerie) in the twin — grasp synthesis, IK (mink), motion
planning (OMPL + MuJoCo collision checks), TOPP-RA timing, execution and validation in MuJoCo physics.

Modules, one concept each:
  world       the MuJoCo world and named access to its state (`World`, `JointMap`: arm, gripper, objects, frames)
  grasp       antipodal grasp synthesis on a collision mesh and ranking
  selection   grasp candidates for the support under an object, place targets at a goal (belief geometry)
  ik / planning / timing / motion   IK (mink), collision checking + OMPL, TOPP-RA, the planning scene
  candidates  feasible grasp + place plans (`plans.GraspPlan`, `plans.PlacePlan`)
  servo / monitor   execution in physics and contact monitoring (`monitor.ContactEvent`)
  judge       grasped / placed / at rest / collisions
  rollout     the recorded rollout (`Rollout`), the single record of what happened in physics
  track       the viewer's robot track (robot/playback.npz) from a rollout
  execute     `Executor`: sequences the units for a task; trials / outputs / cli around it

Entry points: `splattwin plan TWIN --task task.yaml`; in Python `trials.run_once(TrialSpec(...))`,
`trials.run_trials(...)`, `world.build_world(...)`, `execute.Executor(world).run(task)`.
"""

from __future__ import annotations

from splattwin._lazy import lazy_exports

# Lazy: nothing is imported until a name is used (`splattwin --help` imports the options modules only).
_EXPORTS = {"TrialSpec": "trials", "run_once": "trials", "run_trials": "trials", "summarize_trials": "trials",
            "BasePose": "world", "World": "world", "build_world": "world", "Executor": "execute",
            "RunResult": "execute", "Task": "task", "load_task": "task", "parse_task": "task",
            "default_task_path": "task", "Rollout": "rollout", "RobotOptions": "options", "ensure_panda": "assets",
            "panda_model_path": "assets"}

__all__ = list(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
