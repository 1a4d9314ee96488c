"""Readers of every input format (flight-controller logs, ULog, Betaflight blackbox, ArduPilot DataFlash,
third-party CSV) into a :class:`~gyrocore.data.recording.Recording`."""
