"""The emulated FAST-Hex: physics, sensor models and device emulators speaking the real bytes."""
