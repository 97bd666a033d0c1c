"""ddyn.codegen: C code generated from the one vehicle model (CasADi) and from the DBC (cantools)."""
