"""Fault drills against real processes on loopback (`archery drill`, `services.drills.runner`)."""
