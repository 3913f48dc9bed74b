"""The robot traffic in ns-3's 802.11ax model, the network reference of ``wifi crosscheck``.

One ns-3 run (:func:`run_ns3`) puts ``N`` HE stations and one AP on a 5 GHz channel (spectrum
PHY, log-distance loss, stations 2 m from the AP: no frame errors at any MCS), fixes the data
MCS (``ConstantRateWifiManager``; control frames at the MCS's non-HT reference rate), and runs
the traffic of paper Table II: every ``period`` each station sends its camera frame as UDP
datagrams of at most 1472 bytes (IP MTU 1500); when the AP has received all of them it sends the
station's 32-byte state frame. A frame counts as delivered if the state frame reaches the
station within the period ([deadline] with ``tau = 1``).

``access="su"``: every frame by EDCA (stations contend; A-MPDU with block ack agreements).
``access="ofdma"``: the AP runs ns-3's ``RrMultiUserScheduler`` (DL OFDMA, UL OFDMA solicited by
basic Trigger frames after BSRP Trigger frames, channel access requested every
``access_req_interval_us``); stations keep contending by EDCA as ns-3 lets them.
``access="ofdma-muedca"``: the same, and the AP's MU EDCA Parameter Set (AIFSN 0, the longest
timer) stops a station contending once it has been triggered, as our cell model assumes.

The scenario runs in C++ (compiled once per process by cppyy): ns-3's Python bindings are
the optional dependency ``ns3`` (``pip install codesign-mb[ns3]``), imported on first use.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["NS3_ACCESS", "Ns3Result", "Ns3Scenario", "ns3_available", "run_ns3"]

NS3_ACCESS = ("su", "ofdma", "ofdma-muedca")

UDP_PAYLOAD_MAX_BYTES = 1472
"""UDP payload of a 1500-byte IP MTU: 1500 - IP 20 - UDP 8."""

_HARNESS = r"""
#include "ns3/core-module.h"
#include "ns3/network-module.h"
#include "ns3/internet-module.h"
#include "ns3/wifi-module.h"
#include "ns3/mobility-module.h"
#include "ns3/spectrum-module.h"
#include <cstring>
#include <sstream>
#include <vector>

namespace codesign_xc {
using namespace ns3;

class Harness {
public:
  uint32_t nSta = 0, nFrames = 0, dlBytes = 32;
  std::vector<uint32_t> sizes;
  Time period;
  std::vector<Ptr<Socket>> staTx, apTx;
  std::vector<std::vector<int64_t>> capture, ulDone, dlDone;
  std::vector<std::vector<uint32_t>> ulCount;

  static Ptr<Packet> Make(uint32_t i, uint32_t f, uint32_t size) {
    std::vector<uint8_t> buf(std::max<uint32_t>(size, 8), 0);
    std::memcpy(buf.data(), &i, 4);
    std::memcpy(buf.data() + 4, &f, 4);
    return Create<Packet>(buf.data(), size);
  }
  void SendFrame(uint32_t i, uint32_t f) {
    capture[i][f] = Simulator::Now().GetNanoSeconds();
    for (uint32_t s : sizes) { staTx[i]->Send(Make(i, f, s)); }
    if (f + 1 < nFrames) {
      Simulator::Schedule(period, &Harness::SendFrame, this, i, f + 1);
    }
  }
  void ApRecv(Ptr<Socket> sock) {
    Ptr<Packet> p;
    while ((p = sock->Recv())) {
      uint32_t h[2];
      p->CopyData(reinterpret_cast<uint8_t*>(h), 8);
      if (h[0] >= nSta || h[1] >= nFrames) continue;
      if (++ulCount[h[0]][h[1]] == sizes.size()) {
        ulDone[h[0]][h[1]] = Simulator::Now().GetNanoSeconds();
        apTx[h[0]]->Send(Make(h[0], h[1], dlBytes));
      }
    }
  }
  void StaRecv(Ptr<Socket> sock) {
    Ptr<Packet> p;
    while ((p = sock->Recv())) {
      uint32_t h[2];
      p->CopyData(reinterpret_cast<uint8_t*>(h), 8);
      if (h[0] >= nSta || h[1] >= nFrames) continue;
      if (dlDone[h[0]][h[1]] < 0) dlDone[h[0]][h[1]] = Simulator::Now().GetNanoSeconds();
    }
  }
};

// Returns, per station and frame, capture time, UL completion and DL arrival (ns, -1: never).
std::vector<int64_t> RunScenario(uint32_t nSta, uint32_t mcs, uint32_t widthMhz, uint32_t giNs,
                                 bool ofdma, bool muEdca, uint32_t muStations,
                                 double accessReqUs,
                                 std::vector<int64_t> offsetsNs, double periodMs,
                                 uint32_t nFrames, double warmupS, std::vector<uint32_t> sizes,
                                 uint32_t dlBytes, uint32_t run, int64_t rtsThreshold,
                                 double apBeTxopUs) {
  RngSeedManager::SetSeed(1);
  RngSeedManager::SetRun(run);
  if (ofdma) {
    Config::SetDefault("ns3::WifiDefaultAckManager::DlMuAckSequenceType",
                       EnumValue(WifiAcknowledgment::DL_MU_AGGREGATE_TF));
  }
  NodeContainer staNodes; staNodes.Create(nSta);
  NodeContainer apNode; apNode.Create(1);
  auto channel = CreateObject<MultiModelSpectrumChannel>();
  channel->AddPropagationLossModel(CreateObject<LogDistancePropagationLossModel>());
  SpectrumWifiPhyHelper phy;
  phy.SetChannel(channel);
  phy.Set("ChannelSettings", StringValue("{0, " + std::to_string(widthMhz) + ", BAND_5GHZ, 0}"));
  WifiHelper wifi;
  wifi.SetStandard(WIFI_STANDARD_80211ax);
  std::ostringstream dataMode, ctrlMode;
  dataMode << "HeMcs" << mcs;
  ctrlMode << "OfdmRate" << HePhy::GetNonHtReferenceRate(mcs) / 1e6 << "Mbps";
  wifi.SetRemoteStationManager("ns3::ConstantRateWifiManager", "DataMode",
                               StringValue(dataMode.str()), "ControlMode",
                               StringValue(ctrlMode.str()));
  wifi.ConfigHeOptions("GuardInterval", TimeValue(NanoSeconds(giNs)));
  WifiMacHelper mac;
  Ssid ssid("codesign-xc");
  mac.SetType("ns3::StaWifiMac", "Ssid", SsidValue(ssid));
  NetDeviceContainer staDev = wifi.Install(phy, mac, staNodes);
  if (ofdma) {
    mac.SetMultiUserScheduler("ns3::RrMultiUserScheduler", "EnableUlOfdma", BooleanValue(true),
                              "EnableBsrp", BooleanValue(true), "NStations",
                              UintegerValue(muStations), "AccessReqInterval",
                              TimeValue(MicroSeconds(accessReqUs)));
  }
  if (ofdma && muEdca) {
    // MU EDCA Parameter Set: AIFSN 0 (EDCA disabled) for the longest MU EDCA timer
    // (255 x 8.192 ms) after every Trigger frame: triggered stations stop contending.
    TimeValue timer(MicroSeconds(2088960));
    wifi.ConfigHeOptions("MuBeAifsn", UintegerValue(0), "MuBkAifsn", UintegerValue(0),
                         "MuViAifsn", UintegerValue(0), "MuVoAifsn", UintegerValue(0),
                         "BeMuEdcaTimer", timer, "BkMuEdcaTimer", timer,
                         "ViMuEdcaTimer", timer, "VoMuEdcaTimer", timer);
  }
  mac.SetType("ns3::ApWifiMac", "Ssid", SsidValue(ssid), "EnableBeaconJitter",
              BooleanValue(false));
  NetDeviceContainer apDev = wifi.Install(phy, mac, apNode);
  if (rtsThreshold >= 0) {  // RTS/CTS before every PSDU longer than the threshold
    for (const auto& devices : {staDev, apDev}) {
      for (uint32_t i = 0; i < devices.GetN(); ++i) {
        DynamicCast<WifiNetDevice>(devices.Get(i))->GetRemoteStationManager()->SetAttribute(
            "RtsCtsThreshold", UintegerValue(static_cast<uint32_t>(rtsThreshold)));
      }
    }
  }
  if (apBeTxopUs > 0) {
    // The AP's own AC_BE TXOP limit (its dot11QAPEDCATable entry); the EDCA Parameter Set
    // it advertises keeps 0 for the stations.
    auto apMac = DynamicCast<WifiNetDevice>(apDev.Get(0))->GetMac();
    apMac->SetAttribute("TxopLimitsForSta", StringValue("BE 0us"));
    apMac->GetQosTxop(AC_BE)->SetTxopLimit(MicroSeconds(static_cast<int64_t>(apBeTxopUs)));
  }
  int64_t stream = 100;
  stream += WifiHelper::AssignStreams(apDev, stream);
  stream += WifiHelper::AssignStreams(staDev, stream);

  MobilityHelper mobility;
  auto pos = CreateObject<ListPositionAllocator>();
  pos->Add(Vector(0.0, 0.0, 0.0));
  for (uint32_t i = 0; i < nSta; ++i) {
    double a = 2.0 * M_PI * i / nSta;
    pos->Add(Vector(2.0 * std::cos(a), 2.0 * std::sin(a), 0.0));
  }
  mobility.SetPositionAllocator(pos);
  mobility.SetMobilityModel("ns3::ConstantPositionMobilityModel");
  mobility.Install(apNode);
  mobility.Install(staNodes);

  InternetStackHelper stack;
  stack.Install(apNode);
  stack.Install(staNodes);
  Ipv4AddressHelper address;
  address.SetBase("10.1.0.0", "255.255.0.0");
  Ipv4InterfaceContainer staIf = address.Assign(staDev);
  Ipv4InterfaceContainer apIf = address.Assign(apDev);
  NeighborCacheHelper().PopulateNeighborCache();

  Harness h;
  h.nSta = nSta; h.nFrames = nFrames; h.dlBytes = dlBytes; h.sizes = sizes;
  h.period = MicroSeconds(static_cast<int64_t>(periodMs * 1000.0));
  h.capture.assign(nSta, std::vector<int64_t>(nFrames, -1));
  h.ulDone = h.capture; h.dlDone = h.capture;
  h.ulCount.assign(nSta, std::vector<uint32_t>(nFrames, 0));
  TypeId udp = UdpSocketFactory::GetTypeId();
  Ptr<Socket> apRx = Socket::CreateSocket(apNode.Get(0), udp);
  apRx->Bind(InetSocketAddress(Ipv4Address::GetAny(), 9000));
  apRx->SetRecvCallback(MakeCallback(&Harness::ApRecv, &h));
  std::vector<Ptr<Socket>> staRx;
  for (uint32_t i = 0; i < nSta; ++i) {
    Ptr<Socket> tx = Socket::CreateSocket(staNodes.Get(i), udp);
    tx->Bind();
    tx->Connect(InetSocketAddress(apIf.GetAddress(0), 9000));
    h.staTx.push_back(tx);
    Ptr<Socket> rx = Socket::CreateSocket(staNodes.Get(i), udp);
    rx->Bind(InetSocketAddress(Ipv4Address::GetAny(), 9001));
    rx->SetRecvCallback(MakeCallback(&Harness::StaRecv, &h));
    staRx.push_back(rx);
    Ptr<Socket> down = Socket::CreateSocket(apNode.Get(0), udp);
    down->Bind();
    down->Connect(InetSocketAddress(staIf.GetAddress(i), 9001));
    h.apTx.push_back(down);
    Simulator::Schedule(Seconds(warmupS) + NanoSeconds(offsetsNs[i]), &Harness::SendFrame, &h,
                        i, 0u);
  }
  Simulator::Stop(Seconds(warmupS) + h.period * (nFrames + 1));
  Simulator::Run();
  std::vector<int64_t> out;
  out.reserve(3 * nSta * nFrames);
  for (uint32_t i = 0; i < nSta; ++i)
    for (uint32_t f = 0; f < nFrames; ++f) {
      out.push_back(h.capture[i][f]);
      out.push_back(h.ulDone[i][f]);
      out.push_back(h.dlDone[i][f]);
    }
  Simulator::Destroy();
  return out;
}
}  // namespace codesign_xc
"""


def ns3_available() -> bool:
    """Whether ns-3's Python bindings (the optional ``ns3`` dependency) can be imported."""
    import importlib.util

    return importlib.util.find_spec("ns") is not None


@cache
def _harness() -> Any:
    """Import ns-3 (about 15 s) and compile the scenario once per process."""
    try:
        from ns import ns  # noqa: F401  (loads ns-3's libraries and headers into cppyy)
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise RuntimeError(
            "ns-3 is not installed: pip install 'codesign-mb[ns3]' (ns3==3.44.post0)"
        ) from exc
    import cppyy

    cppyy.cppdef(_HARNESS)
    return cppyy.gbl.codesign_xc


@dataclass(frozen=True)
class Ns3Scenario:
    """One ns-3 run: cell, access scheme and traffic.

    Parameters
    ----------
    n_stations:
        Robots (HE stations).
    mcs:
        HE-MCS of every data frame, both ways.
    access:
        ``"su"`` (EDCA, single-user PPDUs), ``"ofdma"`` (``RrMultiUserScheduler``) or
        ``"ofdma-muedca"`` (the same, triggered stations kept off EDCA by MU EDCA).
    bandwidth_mhz, guard_interval_us:
        Channel width and the HE guard interval of every PPDU (ns-3 has one setting; UL
        OFDMA needs 1.6 or 3.2 us).
    capture:
        ``"staggered"`` (offset ``floor(i * period / N)`` in whole ms) or ``"synchronised"``.
    frames:
        Camera frames per station counted (after ``skip_frames`` that set up block acks).
    mu_stations:
        ``NStations`` of the round-robin scheduler: most stations per MU PPDU.
    access_req_interval_us:
        How often the MU scheduler asks for the channel when the AP has nothing to send.
    rts_cts_threshold_bytes:
        RTS/CTS protects every PSDU longer than this (ns-3 ``RtsCtsThreshold``; ``None``:
        ns-3's default, no RTS for these frames). With synchronised captures a collision then
        costs an RTS, not a whole A-MPDU.
    ap_txop_limit_us:
        The AP's own AC_BE TXOP limit (0: none, a single frame exchange per access); a
        multiple of 32 us up to 8 160 us (the TXOP Limit field of the EDCA Parameter Set
        element counts 255 units of 32 us at most, IEEE 802.11-2020). The stations keep 0.
    """

    n_stations: int
    mcs: int
    access: str = "ofdma"
    bandwidth_mhz: int = 40
    guard_interval_us: float = 1.6
    capture: str = "staggered"
    ul_frame_bytes: int = 13_500
    dl_frame_bytes: int = 32
    period_ms: float = 40.0
    frames: int = 25
    skip_frames: int = 2
    mu_stations: int = 9
    access_req_interval_us: float = 1000.0
    warmup_s: float = 1.0
    run: int = 1
    rts_cts_threshold_bytes: int | None = None
    ap_txop_limit_us: float = 0.0

    def __post_init__(self) -> None:
        if self.access not in NS3_ACCESS:
            raise ValueError(f"access must be one of {NS3_ACCESS}, got {self.access!r}")
        if self.capture not in ("staggered", "synchronised"):
            raise ValueError(f"capture must be staggered or synchronised, got {self.capture!r}")
        if not 1 <= self.n_stations <= 200:
            raise ValueError(f"n_stations must be in [1, 200], got {self.n_stations!r}")
        if not 0 <= self.mcs <= 11:
            raise ValueError(f"mcs must be in [0, 11], got {self.mcs!r}")
        if self.access != "su" and self.guard_interval_us < 1.6:
            raise ValueError("guard_interval_us must be 1.6 or 3.2 with UL OFDMA (HE TB PPDU)")
        if self.frames < 1 or self.skip_frames < 0:
            raise ValueError("frames must be >= 1 and skip_frames >= 0")
        if not (0 <= self.ap_txop_limit_us <= 8160 and self.ap_txop_limit_us % 32 == 0):
            raise ValueError(
                f"ap_txop_limit_us must be a multiple of 32 in [0, 8160], got "
                f"{self.ap_txop_limit_us!r}"
            )
        if self.rts_cts_threshold_bytes is not None and self.rts_cts_threshold_bytes < 0:
            raise ValueError("rts_cts_threshold_bytes must be >= 0 or None")

    def datagram_sizes(self) -> list[int]:
        """The camera frame as UDP datagrams of at most 1472 bytes."""
        full, rest = divmod(self.ul_frame_bytes, UDP_PAYLOAD_MAX_BYTES)
        return [UDP_PAYLOAD_MAX_BYTES] * full + ([rest] if rest else [])

    def offsets_ns(self) -> list[int]:
        """Capture offsets of the stations within the period (whole ms, as our cell)."""
        if self.capture == "synchronised":
            return [0] * self.n_stations
        period_ms = round(self.period_ms)
        return [(i * period_ms // self.n_stations) * 1_000_000 for i in range(self.n_stations)]


@dataclass(frozen=True)
class Ns3Result:
    """Per frame (station x frame) capture, UL-complete and DL-arrival times, in ms (NaN: never)."""

    scenario: Ns3Scenario
    capture_ms: NDArray[np.float64]
    ul_done_ms: NDArray[np.float64]
    dl_done_ms: NDArray[np.float64]

    @property
    def latency_ms(self) -> NDArray[np.float64]:
        """Capture to state-frame arrival of every counted frame (NaN: not delivered)."""
        return (self.dl_done_ms - self.capture_ms)[:, self.scenario.skip_frames :]

    @property
    def delivered_fraction(self) -> float:
        """Frames whose state frame arrived within the period (``tau = 1``)."""
        lat = self.latency_ms
        ok = np.isfinite(lat) & (lat <= self.scenario.period_ms + 1e-9)
        return float(ok.mean())


def run_ns3(scenario: Ns3Scenario) -> Ns3Result:
    """Run one ns-3 scenario (deterministic for its ``run`` number)."""
    xc = _harness()
    import cppyy

    s = scenario
    offsets = cppyy.gbl.std.vector["int64_t"](s.offsets_ns())
    sizes = cppyy.gbl.std.vector["uint32_t"](s.datagram_sizes())
    n_frames = s.frames + s.skip_frames
    raw = xc.RunScenario(
        s.n_stations,
        s.mcs,
        s.bandwidth_mhz,
        round(s.guard_interval_us * 1000),
        s.access != "su",
        s.access == "ofdma-muedca",
        s.mu_stations,
        float(s.access_req_interval_us),
        offsets,
        float(s.period_ms),
        n_frames,
        float(s.warmup_s),
        sizes,
        s.dl_frame_bytes,
        s.run,
        -1 if s.rts_cts_threshold_bytes is None else int(s.rts_cts_threshold_bytes),
        float(s.ap_txop_limit_us),
    )
    arr = np.asarray(list(raw), dtype=float).reshape(s.n_stations, n_frames, 3)
    arr = np.where(arr < 0, math.nan, arr / 1e6)
    return Ns3Result(s, arr[..., 0], arr[..., 1], arr[..., 2])
