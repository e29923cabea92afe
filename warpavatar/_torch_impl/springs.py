"""Work in progress: being written (placeholder so that imports resolve)."""


def spring_step(*args, **kwargs):
    raise NotImplementedError("spring_step is being written")


def isometry_loss(*args, **kwargs):
    raise NotImplementedError("isometry_loss is being written")


def damping_loss(*args, **kwargs):
    raise NotImplementedError("damping_loss is being written")
