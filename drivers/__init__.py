"""Real device drivers implementing :mod:`polrig.hal`, chosen by the rig configuration
(:data:`polrig.rig.DRIVERS`).

=================  ==========================  ============================================
module             device                      transport / protocol
=================  ==========================  ============================================
``genicam_camera`` any GenICam camera          GenTL producer (.cti) through harvesters
``ell14``          Thorlabs Elliptec ELL14     serial 9600 8N1, ELLx ASCII protocol
``k10cr1``         Thorlabs K10CR1             FTDI serial 115200 RTS/CTS, APT binary
``grbl``           GRBL 1.1 rotary turntable   serial 115200, G-code + real-time bytes
``dc2200``         Thorlabs DC2200 LED driver  USB-TMC via pyusb, SCPI
=================  ==========================  ============================================

Every blocking call takes a timeout; failures are typed (:mod:`polrig.errors`). Each driver
is tested against an emulator in :mod:`drivers.emulators` that speaks the same bytes.
"""
