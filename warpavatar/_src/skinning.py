"""Work in progress: being written (placeholder so that imports resolve)."""


def sample_grid(*args, **kwargs):
    raise NotImplementedError("sample_grid is being written")


def lbs(*args, **kwargs):
    raise NotImplementedError("lbs is being written")


def inverse_lbs(*args, **kwargs):
    raise NotImplementedError("inverse_lbs is being written")
