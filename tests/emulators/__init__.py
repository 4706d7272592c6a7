"""Device emulators for the motor tests: a Dynamixel X-series (Protocol 2.0) and a line-protocol controller,
each a byte-in/byte-out model, served on a pseudo-terminal by PtyDevice."""
