"""LinuxCNC integration: thermal compensation through the controller's external offsets.

LinuxCNC (the open-source CNC controller, Debian package ``linuxcnc-uspace``) adds an
*external offset* to an axis: the changes of ``axis.L.eoffset-counts`` x ``axis.L.eoffset-scale``
while ``axis.L.eoffset-enable`` is true and the machine is on and homed, rate-limited by the INI's ``[AXIS_L]OFFSET_AV_RATIO``
(a fraction of the axis's velocity and acceleration reserved for the offset). That is the
controller's own way to add a correction to an axis, and where thermal compensation goes.

* :mod:`.component`: ``thermbench linuxcnc component MODEL_DIR``, a userspace HAL
  component (``loadusr``) that reads the axis position and velocity pins and the
  temperature pins, steps the exported model in the C runtime (the same cycle rules as the
  OPC UA compensator, :mod:`thermbench.compensator.control`) and writes the compensation
  to the external offset pins.
* :mod:`.plant`: ``thermbench linuxcnc plant``, a simulated thermal plant for a LinuxCNC
  simulator configuration: the ball-screw simulator (seed 000) driven by the axis's real
  motion on a scaled clock, publishing the temperature pins the component reads.
* :mod:`.sim`: ``thermbench linuxcnc sim MODEL_DIR``: writes a headless LinuxCNC sim
  configuration (INI, HAL, a G-code duty cycle, a display program on LinuxCNC's Python
  ``linuxcnc`` module instead of a GUI), runs it, and checks the closed loop
  (:mod:`.verify`).

docs/linuxcnc.md has the HAL snippet and INI lines for a real machine.
"""
