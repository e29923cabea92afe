"""Work in progress: being written (placeholder so that imports resolve)."""


def rasterize_gaussians(*args, **kwargs):
    raise NotImplementedError("rasterize_gaussians is being written")
