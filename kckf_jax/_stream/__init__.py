"""Live filtering, in three concepts: packets and their parser (``_packets.py``), the
``StreamingFilter`` over the batch filter's step (``_filter.py``), and sources, sinks and the
loop that joins them (``_io.py``; the Lab Streaming Layer's in ``_lsl.py``)."""

from ._filter import LOW_LATENCY_XLA_FLAGS as LOW_LATENCY_XLA_FLAGS
from ._filter import StreamingFilter as StreamingFilter
from ._filter import low_latency as low_latency
from ._filter import stream_step_fn as stream_step_fn
from ._io import ReplaySource as ReplaySource
from ._io import SerialSource as SerialSource
from ._io import StdoutSink as StdoutSink
from ._io import UdpSink as UdpSink
from ._io import UdpSource as UdpSource
from ._io import open_sink as open_sink
from ._io import open_source as open_source
from ._io import replay_path as replay_path
from ._io import run_stream as run_stream
from ._lsl import LslSink as LslSink
from ._lsl import LslSource as LslSource
from ._lsl import lsl_loopback_config as lsl_loopback_config
from ._packets import STATUSES as STATUSES
from ._packets import USED as USED
from ._packets import Packet as Packet
from ._packets import PacketParser as PacketParser
from ._source import Foreign as Foreign
from ._source import Handover as Handover
from ._source import Oversized as Oversized
from ._source import Source as Source
