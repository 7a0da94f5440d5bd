//! Fixed-capacity storage: pools with typed ids, and the queues that join the real-time part of
//! the mapper to its background part.

mod pool;

pub use pool::{Pool, PoolId, Slot};

/// Single-producer single-consumer queue of fixed capacity (lock-free, usable from an interrupt
/// or a second thread). Re-exported from `heapless`.
pub use heapless::spsc::Queue as SpscQueue;
/// Double-ended queue of fixed capacity. Re-exported from `heapless`.
pub use heapless::Deque;

crate::typed_id!(
    /// Id of a frame node in the pose graph.
    NodeId
);
crate::typed_id!(
    /// Id of an edge (constraint) in the pose graph.
    EdgeId
);
crate::typed_id!(
    /// Id of an occupancy-grid submap.
    SubmapId
);
