"""Software-in-the-loop vehicle and mocap: ``groundstation sitl``.

Pure core: :mod:`.scene` (structures), :mod:`.physics` (rigid body, contact), :mod:`.control`,
:mod:`.imu_model`, :mod:`.gusts`, :mod:`.pilots`, :mod:`.vehicle` (failsafe), :mod:`.truth`,
:class:`.runner.Simulation` (timestamped wire bytes on a simulated clock). Thin shells:
:func:`.runner.run_paced`, :mod:`.transport` (pty, UDP); the command is ``groundstation.cli.sitl``.
"""
