"""The programs: the `archery` CLI and everything a person runs that is not one of the five
services (up, demo, dashboard, topic tools, keys, drills, experiment, report, learn). Programs may
import anything; nothing imports a program."""
