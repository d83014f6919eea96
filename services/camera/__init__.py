"""The camera: frames of the target from a renderer, a real device or an image folder."""
