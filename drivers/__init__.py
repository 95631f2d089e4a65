"""Device drivers: one subpackage per device (codec, transport, device), no knowledge of the
estimator, controller or simulator."""
