"""User-facing errors: the CLI prints their message on one line and exits with code 2."""


class RlsacError(Exception):
    """Bad input or configuration that the user can fix (missing file, wrong shape, NaN...)."""
