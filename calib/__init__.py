"""Material calibration workflow and the ``phantom-calib`` command line."""

__all__: list[str] = []
