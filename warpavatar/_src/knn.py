"""Work in progress: being written (placeholder so that imports resolve)."""


def knn_graph(*args, **kwargs):
    raise NotImplementedError("knn_graph is being written")
