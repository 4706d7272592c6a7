"""Motors: the driver interface and safety layer (base), the simulated motor, Dynamixel Protocol 2.0 and a
line protocol over serial, and the actuator loop that ties them to commands (runner). No zenoh here."""

from .base import Disconnected, Driver, MotorError, MotorSettings, NoAnswer, PortError, Safety, TransientError

__all__ = ["Disconnected", "Driver", "MotorError", "MotorSettings", "NoAnswer", "PortError", "Safety",
           "TransientError",
           "make_driver", "check_driver", "DRIVERS", "PORTED"]

DRIVERS = ("sim", "dynamixel", "line", "ros2")
PORTED = ("dynamixel", "line", "ros2")  # the drivers that take a port (ros2's: a controller, vergence/motors/ros2.py)
SERIAL = ("dynamixel", "line")  # ... and those that cannot start without one


def check_driver(name: str, port: str = "", given: str | None = None) -> None:
    """Whether driver `name` can start with `port` (the settings' and the command line's together), before
    anything starts: ValueError naming the choices, or the option that does not apply. given: the port as the
    command line gave it (--port), which the sim driver refuses rather than ignores."""
    if name not in DRIVERS:
        raise ValueError(f"unknown driver {name!r}; choose one of {', '.join(DRIVERS)}")
    if given and name not in PORTED:
        raise ValueError(f"--port applies to a real driver ({', '.join(PORTED)}); the {name} driver has no port")
    if name in SERIAL and not port:
        raise ValueError(f"driver {name!r} needs a serial port: pass --port URL (e.g. /dev/ttyUSB0) or set "
                         "[actuator] port; list ports with `python -m serial.tools.list_ports -v`")


def make_driver(name: str, settings: MotorSettings, port: str = "", lies: dict | None = None) -> Driver:
    """The driver called `name` (sim | dynamixel | line | ros2) for the motor `settings` on `port` (pyserial URL);
    lies: the sim motor's (SimMotor's stall, noise_deg: `vergence actuator --faults`), refused for any other."""
    if lies and name != "sim":
        raise ValueError(f"--faults makes the sim motor lie; the {name} driver drives a real one")
    if name == "sim":
        from .simulated import SimMotor
        return SimMotor(settings, **(lies or {}))
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
