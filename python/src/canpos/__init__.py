"""canpos from Python: the `canpos` binary this wheel carries, a client of its control
interface, and the processes behind the pytest fixtures (`canpos.pytest_plugin`)."""
from .control import ControlClient, ControlError
from .process import Bus, Sensor, binary, free_port

__all__ = ["Bus", "ControlClient", "ControlError", "Sensor", "binary", "free_port"]
