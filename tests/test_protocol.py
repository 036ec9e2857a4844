import msgpack
import numpy as np
import pytest

from shared.protocol import (INLINE_ARRAY_BYTES, ErrorCode, ErrorReply, Hello, InferReply, InferRequest, Metadata,
                             ModelInfo, Ping, Pong, ProtocolError, Timings, decode, encode, pack_header)


def request(rng=np.random.default_rng(0)) -> InferRequest:
    return InferRequest(id="r-1", robot="arm-7", model="pi0", instruction="pick up the cup",
                        images={"base": rng.integers(0, 256, (224, 224, 3), dtype=np.uint8),
                                "wrist": rng.integers(0, 256, (224, 224, 3), dtype=np.uint8)},
                        state=rng.standard_normal(32).astype(np.float32))


def test_infer_request_round_trip_with_zero_copy_frames():
    req = request()
    frames = encode(req)
    assert len(frames) == 3  # header + two image frames; the 128-byte state travels inline
    # Encoding does not copy: each image frame is a view of the caller's array.
    assert np.shares_memory(np.frombuffer(frames[1], np.uint8), req.images["base"])
    wire = [bytes(f) for f in frames]  # what ZeroMQ delivers
    got = decode(wire)
    assert isinstance(got, InferRequest)
    assert (got.id, got.robot, got.model, got.instruction) == (req.id, req.robot, req.model, req.instruction)
    for cam in req.images:
        np.testing.assert_array_equal(got.images[cam], req.images[cam])
    np.testing.assert_array_equal(got.state, req.state)
    # Decoding does not copy either: the arrays are views of the received frames.
    assert got.images["base"].base is not None and not got.images["base"].flags.writeable


def test_reply_error_and_small_messages_round_trip():
    actions = np.arange(50 * 32, dtype=np.float32).reshape(50, 32)
    got = decode([bytes(f) for f in encode(InferReply("x", "pi0", actions, Timings(1.0, 2.0, 3.0, 6.5)))])
    assert isinstance(got, InferReply) and got.timings == Timings(1.0, 2.0, 3.0, 6.5)
    np.testing.assert_array_equal(got.actions, actions)
    small = np.ones((2, 3), np.float32)
    assert small.nbytes <= INLINE_ARRAY_BYTES and len(encode(InferReply("y", "m", small))) == 1
    err = decode(encode(ErrorReply("z", ErrorCode.SHAPE_MISMATCH, "bad")))
    assert err == ErrorReply("z", ErrorCode.SHAPE_MISMATCH, "bad")
    info = ModelInfo(cameras=["a", "b"], image_shape=[224, 224, 3], state_dim=32, horizon=50, action_dim=32,
                     deadline_ms=156.0, arch="pi0")
    assert decode(encode(Metadata("m", {"pi0": info}))) == Metadata("m", {"pi0": info})
    assert decode(encode(Hello("h"))) == Hello("h")
    assert decode(encode(Ping("p"))) == Ping("p")
    assert decode(encode(Pong("p"))) == Pong("p")


def tamper(frames, fn):
    header = msgpack.unpackb(frames[0])
    fn(header)
    return [pack_header(header), *frames[1:]]


@pytest.mark.parametrize("mutate,fragment", [
    (lambda h: h["obs"]["images"]["base"].update(dtype="complex64"), "dtype"),
    (lambda h: h["obs"]["images"]["base"].update(shape=[224, 224, 4]), "needs"),
    (lambda h: h["obs"]["images"]["base"].update(shape=[2**30, 2**30, 3]), "needs"),
    (lambda h: h["obs"]["images"]["base"].update(shape="big"), "shape"),
    # Zero bytes, as declared, but dims numpy cannot hold: reshape's ValueError answered INTERNAL ("retry") with a
    # traceback in the executor's log, and a reply shaped so failed the SDK's poll() with a bare ValueError.
    (lambda h: h["obs"].update(state={"dtype": "float32", "shape": [0, 2**31 - 1, 2**31 - 1, 2**31 - 1], "data": b""}),
     "beyond what an array can hold"),
    (lambda h: h["obs"]["images"]["base"].update(frame=7), "frame"),
    (lambda h: h["obs"]["images"]["wrist"].update(frame=1), "twice"),
    (lambda h: h["obs"].pop("state"), "state: missing"),
    (lambda h: h.update(model=5), "model: expected str"),
    (lambda h: h.update(robot=None), "robot"),
    (lambda h: h.update(kind="teleport"), "unknown message kind"),
    (lambda h: h.update(v=99), "version"),
    (lambda h: h["obs"].update(instruction=b"\x00"), "instruction"),
    (lambda h: h.update(obs=[]), "obs"),
])
def test_malformed_requests_are_bad_request(mutate, fragment):
    frames = [bytes(f) for f in encode(request())]
    with pytest.raises(ProtocolError) as e:
        decode(tamper(frames, mutate))
    assert e.value.code == ErrorCode.BAD_REQUEST
    assert fragment in e.value.message


def test_frame_count_mismatch_and_garbage():
    frames = [bytes(f) for f in encode(request())]
    for bad in (frames + [b"extra"], frames[:2], [b"\xc1\xff\x00"], [msgpack.packb([1, 2, 3])], []):
        with pytest.raises(ProtocolError) as e:
            decode(bad)
        assert e.value.code == ErrorCode.BAD_REQUEST
    with pytest.raises(ProtocolError) as e:
        decode([b"\x80" + b"x" * 70000])
    assert e.value.code == ErrorCode.TOO_LARGE


def test_arrays_that_cannot_travel_are_refused_at_the_sender():
    with pytest.raises(TypeError):
        encode(InferRequest("x", "r", "m", images={"a": np.zeros(3, dtype=object)}, state=np.zeros(2, np.float32)))


def deep(n: int = 1000):
    """A list nested ``n`` deep: about 1 KB of msgpack, and a RecursionError for repr()."""
    v: list = []
    for _ in range(n):
        v = [v]
    return v


@pytest.mark.parametrize("mutate", [
    lambda h: h.update(v=deep()),
    lambda h: h.update(kind=deep()),
    lambda h: h["obs"]["images"]["base"].update(dtype=deep()),
    lambda h: h["obs"]["images"]["base"].update(frame=deep()),
    lambda h: h["obs"]["images"]["base"].update(shape=deep()),
    lambda h: h.update(model=deep()),
    lambda h: h.update(id=deep()),
])
def test_a_deeply_nested_value_is_a_bad_request_not_a_crash(mutate):
    """Error messages quoted wire values with repr(), which raises RecursionError on a list nested a
    thousand deep: the router then answered nothing, and the SDK raised out of poll()."""
    frames = [bytes(f) for f in encode(request())]
    with pytest.raises(ProtocolError) as e:
        decode(tamper(frames, mutate))
    assert e.value.code == ErrorCode.BAD_REQUEST and len(e.value.message) < 300


def test_big_endian_arrays_arrive_as_the_same_numbers():
    """The wire is little-endian; a big-endian array went out under its dtype's name with its bytes
    unswapped, so 1 arrived as 16777216."""
    inline = np.arange(4, dtype=">i4")
    framed = np.linspace(-1, 1, 400, dtype=">f4")
    frames = [bytes(f) for f in encode(InferRequest("x", "r", "m", images={"a": inline, "b": framed},
                                                    state=np.zeros(2, np.float32)))]
    got = decode(frames)
    assert got.images["a"].tolist() == [0, 1, 2, 3] and got.images["a"].dtype == np.int32
    assert np.array_equal(got.images["b"], framed.astype("<f4"))


@pytest.mark.parametrize("images", [{0: np.zeros(3, np.uint8)},
                                    {f"c{i}": np.zeros(1, np.uint8) for i in range(1025)}])
def test_camera_maps_the_router_cannot_read_are_refused_at_the_sender(images):
    """Camera names that are not strings, or more cameras than a header map holds: the router's decoder
    refuses those before it can read the id, so its answer would carry id "" and the request time out."""
    with pytest.raises((TypeError, ValueError)):
        encode(InferRequest("x", "r", "m", images=images, state=np.zeros(2, np.float32)))
