"""Status values the host reads as soon as the device has written them (``warpavatar._src.graphs.status_mailbox``).

The rasterizer's speculative passes read their pair count and input flags through a mailbox, posted after the
front half of the pass, so the host goes on while the compositing runs. On CUDA the post is an asynchronous copy to
pinned memory, also inside a CUDA graph, and a read returns before the stream is idle; on CPU the post copies at
once.
"""

import pytest
import torch

from warpavatar._src.graphs import status_mailbox as mailboxes
from warpavatar._src.graphs.address_graphs import AddressKeyedGraphs
from warpavatar._src.graphs.status_mailbox import StatusMailbox, status_mailbox


def _is_cuda(device) -> bool:
    return torch.device(device).type == "cuda"


def test_a_read_returns_what_was_posted_since_arming(device):
    device = torch.device(device)
    mailbox = status_mailbox(device, slots=3)
    assert status_mailbox(device, slots=3) is mailbox  # one per thread, device, stream and size
    for values in ([5, 0, 17], [123456, 3, 0], [0, 0, 1]):
        source = torch.tensor(values, dtype=torch.int32, device=device)
        mailbox.arm()
        mailbox.post(source)
        assert mailbox.read() == values


def test_reading_an_empty_mailbox_raises(device, monkeypatch):
    monkeypatch.setattr(mailboxes, "POLL_SECONDS", 1e-3)
    mailbox = StatusMailbox(2, torch.device(device))
    mailbox.arm()
    with pytest.raises(RuntimeError, match="never arrived"):
        mailbox.read()


def test_posting_needs_the_mailbox_layout(device):
    mailbox = StatusMailbox(2, torch.device(device))
    for bad in (torch.zeros(3, dtype=torch.int32, device=device), torch.zeros(2, device=device),
                torch.zeros(4, dtype=torch.int32, device=device)[::2]):
        with pytest.raises(ValueError, match="contiguous int32"):
            mailbox.post(bad)


def test_a_read_returns_while_later_work_still_runs(device):
    if not _is_cuda(device):
        pytest.skip("CPU work runs synchronously")
    device = torch.device(device)
    mailbox = status_mailbox(device)
    source = torch.zeros(2, dtype=torch.int32, device=device)
    for value in (4, 9):
        mailbox.arm()
        source.fill_(value)
        mailbox.post(source)
        torch.cuda._sleep(200_000_000)  # some 0.1 s of later work on the same stream
        assert mailbox.read() == [value, value]
        assert not torch.cuda.current_stream(device).query()  # the read did not wait for the sleep
        torch.cuda.synchronize(device)


def test_a_captured_post_delivers_each_replay_s_values(device):
    # The rasterizer's replayed passes post from inside a CUDA graph (address_graphs): every replay's copy lands
    # in the same pinned block, with that replay's values.
    device = torch.device(device)
    graphs = AddressKeyedGraphs()
    mailbox = status_mailbox(device)
    source = torch.zeros(2, dtype=torch.int32, device=device)
    counts = torch.zeros(2, dtype=torch.int32, device=device)
    key = ("mailbox test", mailbox.address, source.data_ptr(), counts.data_ptr())

    def queue():
        torch.add(counts, source, out=counts)
        mailbox.post(counts)

    expected = torch.zeros(2, dtype=torch.int32)
    for step in range(5):
        source.copy_(torch.tensor([step + 1, 2 * step], dtype=torch.int32))
        expected += torch.tensor([step + 1, 2 * step], dtype=torch.int32)
        mailbox.arm()
        graphs.run(key, queue, device=device)
        assert mailbox.read() == expected.tolist()
    if _is_cuda(device):
        assert graphs.captures == 1 and graphs.replays == 3


def test_the_stream_handle_is_torch_s_current_stream(device):
    if not _is_cuda(device):
        pytest.skip("streams are CUDA's")
    from warpavatar._src.warp_utils import current_stream_handle

    device = torch.device(device)
    assert current_stream_handle(device) == torch.cuda.current_stream(device).cuda_stream
    default_mailbox = status_mailbox(device)
    side = torch.cuda.Stream(device=device)
    with torch.cuda.stream(side):
        assert current_stream_handle(device) == side.cuda_stream
        assert status_mailbox(device) is not default_mailbox  # each stream posts to its own block
