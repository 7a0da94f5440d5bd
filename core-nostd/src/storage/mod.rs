//! The typed ids that address the pose graph's nodes and edges: `u32` newtypes, so a node id
//! cannot be passed where an edge id is meant.

/// Declares a `Copy` newtype id over `u32`.
macro_rules! typed_id {
    ($(#[$meta:meta])* $name:ident) => {
        $(#[$meta])*
        #[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
        #[cfg_attr(feature = "defmt", derive(defmt::Format))]
        pub struct $name(pub u32);
    };
}

typed_id!(
    /// Id of a frame node in the pose graph.
    NodeId
);
typed_id!(
    /// Id of an edge (constraint) in the pose graph.
    EdgeId
);
