//! An administrator's kick on a cluster: every node closes the user's connections to it and
//! refuses them, not just the node the admin asked (`crate::admin`'s `POST /admin/kick`).
//!
//! Two rounds, both requests to every registered node on its kick subject: first each node
//! disconnects whom the order names and answers with those it closed; only if anyone anywhere
//! was closed does the second round tell every node to refuse them for the order's time (so a
//! kick of nobody, say a typo, refuses nobody, as on one node). A node that does not answer is
//! named in the admin's answer.

use std::sync::Arc;
use std::time::Duration;

use brickcast_protocol::wire::UserId;
use bytes::Bytes;
use serde::{Deserialize, Serialize};

use super::jet::{Bucket, Jet, answer_requests};
use super::log::token;

/// How long the asking node waits for each node's answer.
const ANSWER_WAIT: Duration = Duration::from_secs(3);

/// What a kick asks of every node.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Order {
    pub user: Option<UserId>,
    pub name: Option<String>,
    pub scene: Option<String>,
    pub refuse_for_ms: u64,
    pub round: Round,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Round {
    /// Close the connections of whom the order names; answer with those closed.
    Disconnect,
    /// Refuse them for `refuse_for_ms`.
    Refuse,
}

/// A node's kick subject.
pub fn subject(node: &str) -> String {
    format!("brickcast.kick.{}", token(node))
}

/// Sends `order` to every registered node: each node's name and its answer (`None`: it did not
/// answer in time).
pub async fn ask_all(jet: &impl Jet, order: &Order) -> Vec<(String, Option<Bytes>)> {
    let Ok(body) = serde_json::to_vec(order) else {
        return Vec::new();
    };
    let body = Bytes::from(body);
    let mut nodes = jet.kv_keys(Bucket::Nodes).await.unwrap_or_default();
    nodes.sort();
    let asks = nodes.into_iter().map(|node| {
        let body = body.clone();
        async move {
            let answer = jet.request(subject(&node), body, ANSWER_WAIT).await.ok();
            (node, answer)
        }
    });
    futures_util::future::join_all(asks).await
}

/// What a node does with an order: its answer's bytes.
pub type Handler = Arc<dyn Fn(&Order) -> Vec<u8> + Send + Sync>;

/// A node's side: answers the orders on its kick subject until `shutdown`.
pub async fn answer<J: Jet>(
    jet: J,
    node: String,
    handle: Handler,
    shutdown: tokio_util::sync::CancellationToken,
) {
    answer_requests(&jet, subject(&node), "administrators' kicks from other nodes", &shutdown, |payload| {
        // A message this node cannot read (another version, garbage) gets no answer: the
        // asking node names this node as not told.
        let answer = match serde_json::from_slice::<Order>(&payload) {
            Ok(order) => Some(Bytes::from(handle(&order))),
            Err(e) => {
                tracing::warn!(node = %node, error = %e, "a kick order that could not be read was ignored");
                None
            }
        };
        std::future::ready(answer)
    })
    .await;
}
