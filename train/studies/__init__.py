"""Studies: the papers' tables (DDM/DPM, FTHD over data fractions, denoising)."""
