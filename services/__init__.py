"""The five archery services (robot, camera, detector, controller, learner) and the launcher."""
