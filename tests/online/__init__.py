"""Tests of hilbench.online: RLS, the OIIR identifier of paper 000, inverse compensators."""
