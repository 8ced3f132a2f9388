"""Exceptions raised for bad user input (files, patterns, scans). The CLI turns them into one line."""


class InputError(ValueError):
    """Bad input that the user can fix; the message names the problem and, where known, the file."""


class PatternError(InputError):
    """A sewing pattern that cannot be read, validated or meshed."""


class ScanError(InputError):
    """A scan that cannot be read or is unusable (empty, NaN, wrong units…)."""


class SimulationError(RuntimeError):
    """The simulation blew up (NaN, runaway speed or stretch) and returned nothing usable."""
