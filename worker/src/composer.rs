//! Connections to composers, one per address, opened on first use and kept.
//!
//! Results go straight to the composer a batch names (DESIGN.md: not through the master,
//! whose bandwidth is the bottleneck). Each link runs a small reader that logs what the
//! composer says and marks the link dead when it closes, so the next send reconnects
//! instead of writing into a closed socket.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::Duration;

use futures_util::{FutureExt, SinkExt, StreamExt};
use nephele_proto::auth::FarmSecret;
use nephele_proto::stream::{Connection, framed, handshake};
use nephele_proto::{FrameConfig, Message, ProtoError, Role};
use nephele_transport::{FarmStream, FarmTls};
use tokio::sync::Mutex;

type Link = Connection<FarmStream>;

/// The cache of composer links.
#[derive(Debug)]
pub struct ComposerLinks {
    links: Mutex<HashMap<String, Arc<Mutex<Option<Link>>>>>,
    frame: FrameConfig,
    timeout: Duration,
    max_links: usize,
    secret: Option<FarmSecret>,
    tls: Option<FarmTls>,
}

impl ComposerLinks {
    pub fn new(
        frame: FrameConfig,
        timeout: Duration,
        secret: Option<FarmSecret>,
        tls: Option<FarmTls>,
    ) -> ComposerLinks {
        ComposerLinks { links: Mutex::new(HashMap::new()), frame, timeout, max_links: 64, secret, tls }
    }

    /// Sends `message` to the composer at `addr`, connecting (or reconnecting once) as
    /// needed. Sends to one composer are serialised; different composers run in parallel.
    pub async fn send(&self, addr: &str, message: &Message) -> Result<(), ProtoError> {
        let slot = {
            let mut links = self.links.lock().await;
            if !links.contains_key(addr) && links.len() >= self.max_links {
                // Forget links nobody is using right now.
                links.retain(|_, slot| Arc::strong_count(slot) > 1);
            }
            links.entry(addr.to_string()).or_default().clone()
        };
        let mut link = slot.lock().await;
        let mut last_error = ProtoError::Closed;
        for _attempt in 0..2 {
            if link.as_mut().is_some_and(|conn| !drain(addr, conn)) {
                *link = None;
            }
            if link.is_none() {
                match self.connect(addr).await {
                    Ok(conn) => *link = Some(conn),
                    Err(e) => {
                        last_error = e;
                        continue;
                    }
                }
            }
            let Some(conn) = link.as_mut() else { continue };
            match tokio::time::timeout(self.timeout, conn.send(message)).await {
                Ok(Ok(())) => return Ok(()),
                Ok(Err(e)) => last_error = e,
                Err(_) => last_error = ProtoError::Timeout("the composer to take a result"),
            }
            tracing::warn!(composer = addr, error = %last_error, "composer link failed; reconnecting");
            *link = None;
        }
        Err(last_error)
    }

    async fn connect(&self, addr: &str) -> Result<Link, ProtoError> {
        let stream = nephele_transport::connect(addr, self.tls.as_ref(), self.timeout).await?;
        let mut conn = framed(stream, self.frame);
        handshake(&mut conn, Role::Worker, &[Role::Composer, Role::Tool], self.secret.as_ref(), self.timeout).await?;
        tracing::debug!(composer = addr, "connected to composer");
        Ok(conn)
    }
}

/// Reads whatever the composer sent without waiting (it only talks to say something went
/// wrong); `false` if the link is closed or broken.
fn drain(addr: &str, conn: &mut Link) -> bool {
    loop {
        match conn.next().now_or_never() {
            None => return true,
            Some(None) => {
                tracing::info!(composer = addr, "composer closed the link");
                return false;
            }
            Some(Some(Err(e))) => {
                tracing::warn!(composer = addr, "dropping composer link: {e}");
                return false;
            }
            Some(Some(Ok(Ok(Message::Error(e))))) => {
                tracing::warn!(composer = addr, code = ?e.code, "composer says: {}", e.message)
            }
            Some(Some(Ok(Ok(Message::Goodbye(g))))) => {
                tracing::info!(composer = addr, "composer said goodbye: {}", g.reason);
                return false;
            }
            Some(Some(Ok(Ok(other)))) => {
                tracing::debug!(composer = addr, kind = %other.kind(), "ignoring message from composer")
            }
            Some(Some(Ok(Err(rejected)))) => {
                tracing::warn!(composer = addr, "composer sent an invalid message: {rejected}")
            }
        }
    }
}
