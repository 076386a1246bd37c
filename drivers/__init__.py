"""Real device drivers implementing :mod:`polrig.acquisition.hal`, chosen by the rig configuration
(:data:`polrig.app.rig.DRIVERS`).

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
is tested against an emulator in :mod:`polrig.drivers.emulators` that speaks the same bytes.

Each declares its :attr:`~polrig.acquisition.hal.Camera.capabilities` from what the device reports,
read on open (cheap to ask):

=================  =============================================================================
module             capabilities from
=================  =============================================================================
``genicam_camera`` ``TriggerMode``/``TriggerSoftware`` (software trigger, else free run only),
                   ``ExposureTime[Abs]`` min/max, ``SensorReadoutTime`` or one frame period
``ell14``          ``gv`` (velocity, percent of the ELL14's 430 deg/s)
``k10cr1``         ``MOT_REQ_VELPARAMS`` (maximum velocity, acceleration)
``grbl``           ``$$``: ``$11k`` rate, ``$12k`` acceleration, ``$13k`` travel (soft limits)
=================  =============================================================================
"""
