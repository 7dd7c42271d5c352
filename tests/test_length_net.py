import torch

from salad.models.length_net import LengthNet


def _points(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    x = torch.nn.functional.normalize(torch.randn(n, 8, generator=g), dim=-1)
    # captions further along one direction in text space ask for longer motions (0.6-12 s)
    return x, (1 + 1.5 * x[:, 0]).exp()


def test_the_length_net_learns_lengths_from_text_points_and_reads_back_as_written():
    x, seconds = _points(300, 0)
    net = LengthNet.fit(x, seconds, members=2, hidden=64)
    new_x, new_seconds = _points(200, 1)
    error = (net(new_x) / new_seconds - 1).abs()
    assert (error <= 0.1).float().mean() > 0.9, error
    again = LengthNet.fit(x, seconds, members=1, hidden=64)
    assert torch.equal(again(new_x), LengthNet(net.members[:1])(new_x)), "the same data and seed fit the same net"

    tensors = net.tensors()
    read = LengthNet.from_tensors(tensors, 8)
    assert read is not None and len(read.members) == 2
    assert torch.equal(read(new_x), net(new_x))
    assert LengthNet.from_tensors(tensors, 16) is None, "points of another size"
    assert LengthNet.from_tensors({}, 8) is None
    damaged = dict(tensors)
    damaged["length_net.1.2.weight"] = torch.full_like(damaged["length_net.1.2.weight"], float("nan"))
    assert LengthNet.from_tensors(damaged, 8) is None
    del damaged["length_net.1.2.weight"]
    assert LengthNet.from_tensors(damaged, 8) is None, "a member with a layer missing"
