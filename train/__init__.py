"""Offline side of the ddyn stack: vehicle model, simulation, data import, training and analysis."""
