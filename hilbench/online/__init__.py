"""The closed loop: the online identifier and the compensators (paper 000 OIIR, 004 inverse models)."""
