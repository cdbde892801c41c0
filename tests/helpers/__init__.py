"""Shared test code that is not a fixture: builders of test data and small helpers, imported normally
(``from helpers.toy import make_toy``). ``tests/`` is on ``sys.path`` through ``pythonpath`` in
pyproject's ``[tool.pytest.ini_options]``; the conftest.py files hold only fixtures.

- ``helpers.toy``: the toy light-stage capture (a dotted ellipsoid head) of the registration and
  rendering tests.
- ``helpers.capture``: tiny rigs, simulated labs and sessions of the capture tests; the strobe
  controller's recorded transcript.
- ``helpers.tracking``: the tracking tests' synthetic world (cameras, a truth registration) and fault
  injection on copies of a performance folder.
- ``helpers.source_tree``: the source tree as installed modules (packaging, architecture and
  package-root tests).
"""
