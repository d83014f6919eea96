"""Fault drills against real processes on loopback (`archery drill`, `apps.drills.runner`)."""
