"""The composition root: config -> objects, the 500 Hz loop, flight sessions and the CLI."""
