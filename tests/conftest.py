"""Fixtures shared by more than one test folder.

``tiny_chain_notebooks``: the example notebooks ``01_twin_to_c1`` and ``02_validation``
executed once per session at the tiny size. They run the whole chain (synth -> ingest ->
calibrate -> validate) on the tiny fixed-seed twin, which is also the tiny case of the
validation suite (``tests/validation/test_chain.py``): both read this one run instead of
calibrating the same twin twice (in CI the tiny chain went from 227 s to 48 s).
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass, field
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
#: The notebooks of the tiny chain, in the order they share their output folder.
CHAIN_NOTEBOOKS = ("01_twin_to_c1.py", "02_validation.py")
#: The test files that read the tiny chain (``tiny_chain_notebooks``).
CHAIN_FILES = ("test_notebooks.py", "test_chain.py")


def notebooks_available() -> bool:
    """Whether the notebook runner (the ``notebook`` extra: nbclient, jupytext) is here."""
    return all(importlib.util.find_spec(m) is not None for m in ("nbclient", "jupytext"))


def execute_notebook(name: str, out: Path, monkeypatch: pytest.MonkeyPatch):
    """Execute ``examples/<name>`` cell by cell in a real kernel at the tiny size.

    Outputs go to ``out`` (``PHANTOM_CALIB_OUT``); a failing cell raises
    ``nbclient.exceptions.CellExecutionError`` with the cell and its traceback. Returns
    the executed notebook (its cells' outputs).
    """
    import jupytext
    import nbclient

    monkeypatch.setenv("PHANTOM_CALIB_SIZE", "tiny")
    monkeypatch.setenv("PHANTOM_CALIB_OUT", str(out))
    nb = jupytext.read(EXAMPLES / name)
    client = nbclient.NotebookClient(
        nb, timeout=1800, kernel_name="python3", resources={"metadata": {"path": str(EXAMPLES)}}
    )
    client.execute()
    return nb


@dataclass
class NotebookChain:
    """The output folder of the chain notebooks and the error of each that failed."""

    out: Path
    errors: dict[str, BaseException] = field(default_factory=dict)
    executed: dict = field(default_factory=dict)  # name -> the executed notebook

    def images(self, name: str) -> int:
        """How many image/png outputs the executed notebook ``name`` shows."""
        cells = self.executed[name].cells
        return sum("image/png" in o.get("data", {}) for c in cells for o in c.get("outputs", []))

    def run(self, name: str) -> None:
        """Execute notebook ``name`` (after the chain) on the chain's outputs."""
        with pytest.MonkeyPatch.context() as mp:
            self.executed[name] = execute_notebook(name, self.out, mp)

    def require(self, name: str) -> None:
        """Fail the calling test with the notebook's own error if it (or one before) failed."""
        for nb in CHAIN_NOTEBOOKS[: CHAIN_NOTEBOOKS.index(name) + 1]:
            if nb in self.errors:
                raise AssertionError(f"notebook {nb} failed") from self.errors[nb]


@pytest.hookimpl(optionalhook=True)  # a hook of pytest-xdist, where it is installed
def pytest_xdist_make_scheduler(config, log):
    """``--dist loadfile``, with the two files of the tiny chain sent to one worker.

    ``make test`` runs the suite on two workers. Each file's tests go to one worker, so its
    module fixtures are built once; the notebook and validation files share the session's
    tiny chain (:func:`tiny_chain_notebooks`, minutes), so they go to one worker together.
    (xdist's own ``loadgroup`` marks do not reach its scheduler under pytest 9.2.)
    """
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class ChainTogether(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            scope = super()._split_scope(nodeid)
            return "tiny chain" if Path(scope).name in CHAIN_FILES else scope

    return ChainTogether(config, log)


@pytest.fixture
def run_notebook(monkeypatch):
    """``run_notebook(name, out)``: :func:`execute_notebook` with this test's monkeypatch."""
    return lambda name, out: execute_notebook(name, out, monkeypatch)


@pytest.fixture(scope="session")
def tiny_chain_notebooks(tmp_path_factory) -> NotebookChain:
    if not notebooks_available():
        pytest.skip("the notebook extra (nbclient, jupytext) is not installed")
    chain = NotebookChain(tmp_path_factory.mktemp("notebooks"))
    with pytest.MonkeyPatch.context() as mp:
        for name in CHAIN_NOTEBOOKS:
            try:
                chain.executed[name] = execute_notebook(name, chain.out, mp)
            except Exception as exc:  # each test that needs it fails with this error
                chain.errors[name] = exc
                break
    return chain
