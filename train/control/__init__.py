"""Control: MPC set-up shared with the C runtime, the IPOPT reference MPC, racing lines, closed-loop laps."""
