"""The plant: machine parameters and presets, motor models (three-phase, dual three-phase),
the inverter and motor files. Private: the public names are re-exported by `pmsmjax`."""
