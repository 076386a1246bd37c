"""Emulators of the rig's devices, speaking the real bytes over the real transports.

Serial devices (ELL14, K10CR1, GRBL) run on pseudo-terminals (:mod:`._pty`); the DC2200 is a
pyusb backend. They are used by the tests and can be started by hand, e.g.
``python -m polrig.drivers.emulators.ell14 --link /tmp/ell14``, to point a rig config at them.
"""
