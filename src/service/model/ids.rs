//! Ids that cannot be mixed up: a calibration's id passed where a
//! sequence's is expected does not compile. Each is its integer in JSON
//! (`serde(transparent)`) and in SQL (encoded and decoded as a 64-bit integer through sqlx's `Any` driver, `BIGINT` on PostgreSQL),
//! so rows bind and read them directly. Their OpenAPI schema is the HTTP
//! layer's business (`#[schema(value_type = i64)]` on its fields).
//!
//! ```compile_fail
//! # use ptv::service::store::{CalibrationId, Store};
//! # async fn mixed_up(store: &Store) {
//! // A sequence is looked up by a sequence's id only.
//! let _ = store.sequence(CalibrationId(1)).await;
//! # }
//! ```

use std::fmt;

use serde::{Deserialize, Serialize};
use sqlx::any::{AnyTypeInfo, AnyValueRef};
use sqlx::encode::IsNull;
use sqlx::error::BoxDynError;
use sqlx::{Any, Decode, Encode, Type};

/// Declares an id type over `i64`.
macro_rules! id {
    ($(#[$doc:meta])* $name:ident) => {
        $(#[$doc])*
        #[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
        #[serde(transparent)]
        pub struct $name(pub i64);

        impl fmt::Display for $name {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                self.0.fmt(f)
            }
        }

        impl Type<Any> for $name {
            fn type_info() -> AnyTypeInfo {
                <i64 as Type<Any>>::type_info()
            }

            fn compatible(ty: &AnyTypeInfo) -> bool {
                <i64 as Type<Any>>::compatible(ty)
            }
        }

        impl<'q> Encode<'q, Any> for $name {
            fn encode_by_ref(
                &self,
                buf: &mut <Any as sqlx::Database>::ArgumentBuffer<'q>,
            ) -> Result<IsNull, BoxDynError> {
                <i64 as Encode<'q, Any>>::encode_by_ref(&self.0, buf)
            }
        }

        impl<'r> Decode<'r, Any> for $name {
            fn decode(value: AnyValueRef<'r>) -> Result<Self, BoxDynError> {
                <i64 as Decode<'r, Any>>::decode(value).map($name)
            }
        }
    };
}

id!(
    /// A calibration's id.
    CalibrationId
);
id!(
    /// A sequence's id.
    SequenceId
);
id!(
    /// A job's id.
    JobId
);
id!(
    /// A frame's number within its sequence (from 0).
    FrameNumber
);
/// The largest frame number: 4,294,967,295 (`u32::MAX`). Frames are
/// numbered 0 to this in every route (the OpenAPI document says so:
/// `int64`, minimum 0, maximum 4294967295); 4 billion frames are 50 days
/// at 1,000 frames a second, and numbers this small leave the tracker's
/// frame arithmetic (`i64`) far from overflow.
pub const MAX_FRAME_NUMBER: i64 = u32::MAX as i64;

id!(
    /// A tracking run's id.
    TrackingRunId
);
id!(
    /// A lease's fencing token: incremented at every claim of a job (or
    /// change of a tracking run's holder), so that a write fenced on it
    /// fails for every earlier holder.
    LeaseToken
);
id!(
    /// An event's id in the event log: its number on every sequence's
    /// event stream (the SSE `id:`).
    EventId
);
