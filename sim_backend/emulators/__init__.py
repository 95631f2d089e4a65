"""Device emulators: the same bytes as the hardware, over pseudo-terminals and UDP."""
