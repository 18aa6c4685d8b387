"""The twin you can see: a live 3-D view in the browser (``twin view``, docs/view.md).

Small modules, one job each: :mod:`view.scene` (the arm as numpy geometry, pure),
:mod:`view.model` (the twin the view draws: model, scale maps, calibration),
:mod:`view.phases` (the campaign phase at an instant), :mod:`view.sources` (replay and
live samples), :mod:`view.server` (viser wiring), :mod:`view.cli` (the command).
The package imports ``calibration`` and ``daq``; nothing imports it but the command line
(``twin view`` loads it on first use).
"""
