"""Evaluation tooling: statistics (``stats``), comparisons against Mitsuba's built-ins
(``compare``, ``report``), grid inspection (``grid_info``) and the ``mitsuba-plugins``
command line (``cli``). Tooling imports the core package; no plugin and no module of the
core imports tooling (tests/package/test_registration.py checks it)."""
