"""Shared test code that is not a fixture: builders of test data and small helpers, imported normally
(``from helpers.capture import tiny_rig``). ``tests/`` is on ``sys.path`` through ``pythonpath`` in
pyproject's ``[tool.pytest.ini_options]``; the conftest.py files hold only fixtures.

- ``helpers.capture``: tiny rigs, simulated labs and sessions of the capture tests; the strobe
  controller's recorded transcript.
"""
