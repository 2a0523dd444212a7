"""User-facing errors: the CLI prints their message on one line and exits with code 2."""


class RlsacError(Exception):
    """Bad input or configuration that the user can fix (missing file, wrong shape, NaN...)."""

    exit_code = 2


class Interrupted(RlsacError):
    """A run stopped by SIGINT / SIGTERM after saving its state: its MLflow run ends KILLED and the
    command exits 128 + the signal number (130, 143), as a shell reports a killed command."""

    run_status = "KILLED"

    def __init__(self, message: str, signum: int = 15):
        super().__init__(message)
        self.exit_code = 128 + int(signum)
