"""The five archery services: robot, camera, detector, controller, learner (ARCHITECTURE.md)."""
