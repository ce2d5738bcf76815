"""What the scans say: the session, the ingest of every scan, the measurements they give."""

from .measurements import Measurements, ScanMeasurement, load_measurements
from .session import ScanEntry, Session, SessionError, load_session, scaffold_session
from .work import SavedState, WorkFolder, read_work

__all__ = [
    "Measurements",
    "SavedState",
    "ScanEntry",
    "ScanMeasurement",
    "Session",
    "SessionError",
    "WorkFolder",
    "load_measurements",
    "load_session",
    "read_work",
    "scaffold_session",
]
