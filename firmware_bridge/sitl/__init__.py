"""Software-in-the-loop vehicle and mocap: ``groundstation sitl``.

Pure core: :mod:`.scene` (structures), :mod:`.engine` (the physics interface) with two engines,
:mod:`.physics` (``simple``: home-made rigid body, cylinder contact) and :mod:`.mujoco_physics`
(``mujoco``: the :mod:`.airframe`'s real geometry, model written by :mod:`.mjcf`),
:mod:`.control`, :mod:`.imu_model`, :mod:`.gusts`, :mod:`.planner`, :mod:`.pilots`,
:mod:`.maneuvers`, :mod:`.vehicle` (failsafe), :mod:`.truth`, :mod:`.measure` (controlled touch
and gust trials), :class:`.runner.Simulation` (timestamped wire bytes on a simulated clock).
Thin shells: :func:`.runner.run_paced`, :mod:`.transport` (pty, UDP); the command is
``groundstation.cli.sitl``.
"""
