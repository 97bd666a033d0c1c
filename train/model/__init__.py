"""The one vehicle model (numpy, torch, CasADi), vehicles, unmodelled effects, sensors and tracks."""
