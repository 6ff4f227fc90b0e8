"""The applications wing: command lines, thesis studies, converters and reports.

Modules here may import any library package of omnidl; no library package (``cameras``, ``geometry``,
``nn``, ``models``, ``losses``, ``metrics``, ``data``, ``synth``, ``postprocess``, ``engine``,
``search``, ``viz``, ``utils``) ever imports ``omnidl.apps`` (checked by ``tests/test_layering.py``).
"""
