"""The archery task as Gymnasium environments (`archery/Aim-v0`, `archery/AimRobot-v0`; the
`archery[gym]` extra) and the project's learners as their agents. Importing the package
registers the ids (`apps.gym.registration`)."""

from archery.apps.gym.registration import register_envs

register_envs()
