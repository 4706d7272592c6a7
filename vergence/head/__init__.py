"""The head and its time (issue #34: where what a camera and a motor do lands): `timing`, a camera's exposure
instant and the motor's pan history (every pan referred to the instant light reached the sensor); `latency`, the
fit of a camera's latency against the motor's motion; `depth`, the vergence angle's distance; `control`, pixels
to angle and the controllers that turn a decision into a command. The motor drivers are vergence.motors."""
