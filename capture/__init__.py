"""The light stage's hardware side (paper §2): drive it, capture sessions, calibrate the cameras.

Sub-packages and modules (docs/hardware.md is the manual):

* :mod:`.hardware` — the strobe controller's serial protocol (:mod:`.hardware.protocol`:
  framing, CRC, messages), its driver (:mod:`.hardware.controller`, over any pyserial URL),
  strobe sequences as plain data (:mod:`.hardware.sequence`) and the camera interface
  with its backend registry (:mod:`.hardware.cameras`).
* :mod:`.session` — capture sessions: per expression all lights, every camera, the motion
  check (:mod:`.motion`), retakes; an append-only journal (:mod:`.journal`) so an
  interrupted session resumes exactly and nothing captured is ever lost.
* :mod:`.calibration` — geometric (:mod:`.calibration.zhang2000` on ChArUco,
  :mod:`.calibration.charuco`) and radiometric (:mod:`.calibration.debevec1997`,
  :mod:`.calibration.colour_correction`, :mod:`.calibration.radiometric`) calibration.
* :mod:`.simulation` — a simulated lab: the controller speaking the same protocol over a
  pseudo-terminal with fault injection, synthetic cameras rendering the synthetic subject,
  calibration boards rendered by Mitsuba and chart captures.
* :mod:`.cli` — ``mifacerf capture`` and ``mifacerf calibrate …``; :mod:`.benchmark` — the
  measurements in docs/hardware.md.
"""
