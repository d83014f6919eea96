"""Simulation: the MuJoCo iCub scene, arrow physics and the paper's analytic ballistic world."""
