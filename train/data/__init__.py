"""Datasets: the canonical format, importers, training windows, simulation, LCM and CAN logs."""
