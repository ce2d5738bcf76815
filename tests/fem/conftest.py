"""Test configuration of the fem tests."""

from __future__ import annotations

from pathlib import Path

import pytest

_HERE = Path(__file__).resolve().parent

# fem/discretize.py (_geometry) reads ``phi[0].value``, which scikit-fem 12 deprecates
# with a DeprecationWarning; under the project's "warnings are errors" setting every
# solve would fail. Reported to the lead (discretize.py is theirs to change); this
# narrow filter goes away once it reads ``phi[0]`` directly.
_SKFEM_VALUE = "ignore:Writing 'u.value' is unnecessary:DeprecationWarning"


def pytest_collection_modifyitems(config, items):
    for item in items:
        if _HERE in Path(str(item.fspath)).resolve().parents:
            item.add_marker(pytest.mark.filterwarnings(_SKFEM_VALUE))
