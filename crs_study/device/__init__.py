"""The device stage: the CRS display behind LSC-24 boards, real or simulated, chosen by URL.

Layers inside (each module imports only those above it)::

    base          the interface (Device, FrameReport), wire constants, the URL registry
    identity      which board is behind which port: USB serial number, by-id path; the
                  register of boards an experimenter confirmed (device identify)
    calibration   millimetres to whole-us pulse widths and back (PulseMap)
    codec         LSC frames as typed data, and their bytes
    decoder       bytes back to frames: one frame, or a stream with garbage in it
    writes        the host's write policy: what goes on each port, and when (pure)
    schedule      the estimate of a stimulus's wire use and latency; channel balance
    virtual_controller, protocol_lscsim, virtual_pty    a virtual LSC-24 board, as a pyserial
                  URL and as a pseudo-terminal
    virtual_boards  a device file's boards on pseudo-terminals, with taps (device boards)
    serial_port   one board's port: its options, its writer and reader threads
    serial_device the real device: one port per controller
    sim_options   what a sim:// URL sets (timings, injected faults)
    simulated     the simulated device: the same bytes, decoded by virtual boards

``open_device(url, layout, clock)`` looks the URL's scheme up in the registry filled here:
``serial://PORT[,PORT...]`` and ``sim://[?options]``.
"""

from crs_study.device.base import (
    Device,
    DeviceFactory,
    DeviceWarning,
    FrameReport,
    open_device,
    register_scheme,
)
from crs_study.device.serial_device import SerialDevice
from crs_study.device.simulated import SimulatedDevice

register_scheme("serial", SerialDevice.from_url)
register_scheme("sim", SimulatedDevice.from_url)

__all__ = ["Device", "DeviceFactory", "DeviceWarning", "FrameReport", "SerialDevice",
           "SimulatedDevice", "open_device", "register_scheme"]
