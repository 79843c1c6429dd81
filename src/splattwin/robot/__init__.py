"""robot stage: the Franka Panda (MuJoCo Menagerie) in the twin — grasp synthesis, IK (mink), motion
planning (OMPL + MuJoCo collision checks), TOPP-RA timing, execution and validation in MuJoCo physics.

Entry points: `splattwin plan TWIN --task task.yaml`; in Python `trials.run_once(TrialSpec(...))`,
`trials.run_trials(...)`, `world.build_world(...)`, `execute.Executor(world).run(task)`.
"""
