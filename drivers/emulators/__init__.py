"""Emulators: each real driver's device, speaking its protocol on a real transport, backed by a World."""
