"""Motors: the driver interface and safety layer (base), the simulated motor, Dynamixel Protocol 2.0 and a
line protocol over serial, and the actuator loop that ties them to commands (runner). No zenoh here."""

from .base import Disconnected, Driver, MotorError, MotorSettings, NoAnswer, PortError, Safety, TransientError

__all__ = ["Disconnected", "Driver", "MotorError", "MotorSettings", "NoAnswer", "PortError", "Safety",
           "TransientError",
           "make_driver", "DRIVERS"]

DRIVERS = ("sim", "dynamixel", "line", "ros2")


def make_driver(name: str, settings: MotorSettings, port: str = "") -> Driver:
    """The driver called `name` (sim | dynamixel | line | ros2) for the motor `settings` on `port` (pyserial URL)."""
    if name == "sim":
        from .simulated import SimMotor
        return SimMotor(settings)
    if name == "ros2":  # a ros2_control joint; port: CONTROLLER[:joint=NAME...] (vergence/motors/ros2.py)
        from .ros2 import Ros2Driver
        return Ros2Driver(settings, port)
    if name in ("dynamixel", "line"):
        if not port:
            raise PortError(f"driver {name!r} needs a serial port: pass --port URL (e.g. /dev/ttyUSB0) "
                            "or set [actuator] port; list ports with `python -m serial.tools.list_ports -v`")
        if name == "dynamixel":
            from .dynamixel import DynamixelDriver
            return DynamixelDriver(settings, port)
        from .line import LineDriver
        return LineDriver(settings, port)
    raise ValueError(f"unknown driver {name!r}; choose one of {', '.join(DRIVERS)}")
