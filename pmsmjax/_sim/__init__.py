"""The closed loop: scenarios, integration, the simulator, its solution and the metrics of a
run. Private: the public names are re-exported by `pmsmjax`."""
