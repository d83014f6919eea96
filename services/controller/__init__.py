"""The controller service: Eq. 9 inverse kinematics and the archery posture for iCub's arms."""
