//! A UDP socket that holds every datagram for a fixed time each way, given to the `webrtc`
//! crate as the client's one socket (`SettingEngine::set_udp_network` with a UDP mux): a
//! round trip of `2 × one_way` added to the path, in process and without root (this kernel has
//! no `netem`). Order is kept; nothing is lost. `nephele bench glass` measures what the eye
//! sees at 0–150 ms round trips with it.

use std::{
    net::SocketAddr,
    sync::Arc,
    time::Duration,
};

use tokio::{net::UdpSocket, sync::mpsc, time::Instant};
use webrtc::util::Conn;

type UtilResult<T> = Result<T, webrtc::util::Error>;

/// See the module notes.
pub struct DelayedSocket {
    socket: Arc<UdpSocket>,
    inbox: tokio::sync::Mutex<mpsc::UnboundedReceiver<(Instant, Vec<u8>, SocketAddr)>>,
    outbox: mpsc::UnboundedSender<(Instant, Vec<u8>, SocketAddr)>,
    one_way: Duration,
}

impl DelayedSocket {
    /// Wraps `socket`; must be called inside a tokio runtime (it spawns its two pumps).
    pub fn new(socket: UdpSocket, one_way: Duration) -> Self {
        let socket = Arc::new(socket);
        let (in_tx, inbox) = mpsc::unbounded_channel();
        let reader = Arc::clone(&socket);
        tokio::spawn(async move {
            let mut buf = vec![0u8; 2048];
            while let Ok((n, from)) = reader.recv_from(&mut buf).await {
                if in_tx.send((Instant::now() + one_way, buf[..n].to_vec(), from)).is_err() {
                    return;
                }
            }
        });
        let (outbox, mut out_rx) = mpsc::unbounded_channel::<(Instant, Vec<u8>, SocketAddr)>();
        let writer = Arc::clone(&socket);
        tokio::spawn(async move {
            while let Some((due, datagram, to)) = out_rx.recv().await {
                tokio::time::sleep_until(due).await;
                let _ = writer.send_to(&datagram, to).await;
            }
        });
        Self { socket, inbox: tokio::sync::Mutex::new(inbox), outbox, one_way }
    }
}

#[async_trait::async_trait]
impl Conn for DelayedSocket {
    async fn connect(&self, addr: SocketAddr) -> UtilResult<()> {
        Ok(self.socket.connect(addr).await?)
    }

    async fn recv(&self, buf: &mut [u8]) -> UtilResult<usize> {
        Ok(self.recv_from(buf).await?.0)
    }

    async fn recv_from(&self, buf: &mut [u8]) -> UtilResult<(usize, SocketAddr)> {
        let (due, datagram, from) = self.inbox.lock().await.recv().await.ok_or(webrtc::util::Error::ErrUseClosedNetworkConn)?;
        tokio::time::sleep_until(due).await;
        let n = datagram.len().min(buf.len());
        buf[..n].copy_from_slice(&datagram[..n]);
        Ok((n, from))
    }

    async fn send(&self, buf: &[u8]) -> UtilResult<usize> {
        let to = self.socket.peer_addr()?;
        self.send_to(buf, to).await
    }

    async fn send_to(&self, buf: &[u8], target: SocketAddr) -> UtilResult<usize> {
        if self.one_way.is_zero() {
            return Ok(self.socket.send_to(buf, target).await?);
        }
        self.outbox.send((Instant::now() + self.one_way, buf.to_vec(), target)).map_err(|_| webrtc::util::Error::ErrUseClosedNetworkConn)?;
        Ok(buf.len())
    }

    fn local_addr(&self) -> UtilResult<SocketAddr> {
        Ok(self.socket.local_addr()?)
    }

    fn remote_addr(&self) -> Option<SocketAddr> {
        None
    }

    async fn close(&self) -> UtilResult<()> {
        Ok(())
    }

    fn as_any(&self) -> &(dyn std::any::Any + Send + Sync) {
        self
    }
}

/// A [`crate::ClientNet`] whose one socket (on loopback) adds `rtt` to every round trip.
pub async fn delayed_net(rtt: Duration) -> std::io::Result<crate::ClientNet> {
    use webrtc::{
        api::setting_engine::SettingEngine,
        ice::{
            udp_mux::{UDPMuxDefault, UDPMuxParams},
            udp_network::UDPNetwork,
        },
    };
    let socket = UdpSocket::bind((std::net::Ipv4Addr::LOCALHOST, 0)).await?;
    let mux = UDPMuxDefault::new(UDPMuxParams::new(DelayedSocket::new(socket, rtt / 2)));
    Ok(crate::ClientNet {
        settings: Some(Arc::new(move |s: &mut SettingEngine| {
            s.set_udp_network(UDPNetwork::Muxed(mux.clone()));
            // The socket is IPv4: no IPv6 candidate may name it.
            s.set_network_types(vec![webrtc::ice::network_type::NetworkType::Udp4]);
        })),
        ..crate::ClientNet::default()
    })
}
