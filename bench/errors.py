"""Errors the harness raises on purpose: each names the file, sample or name at fault."""


class PcfbenchError(Exception):
    """Base class: a clear, user-facing error (the CLI prints it without a traceback)."""


class DataError(PcfbenchError):
    """A dataset file or table is missing, truncated or malformed."""


class ForecastError(PcfbenchError):
    """A method returned a forecast that breaks the contract (shape, dtype, NaN, range)."""


class UnknownNameError(PcfbenchError, KeyError):
    """An unknown method, dataset, metric or setting name."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


class PluginError(PcfbenchError):
    """A plugin failed to import or registered something invalid."""
