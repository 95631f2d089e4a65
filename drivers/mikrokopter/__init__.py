"""MikroKopter Flight-Ctrl driver: tk3 and stock framings, message codecs, the FlightCtrl device."""
