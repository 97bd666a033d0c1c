"""Code generation (CasADi) from the one vehicle model in train.model."""
