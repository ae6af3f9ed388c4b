"""The simulator's one error: a bad preset, route, camera or output path, named with its value."""

from __future__ import annotations


class SimulationError(ValueError):
    """Bad simulator input; `source` names the option or field and the message gives the value."""

    def __init__(self, source: str, message: str) -> None:
        super().__init__(f"{source}: {message}")
        self.source = source
        self.detail = message
