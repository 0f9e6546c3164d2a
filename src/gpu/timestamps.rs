//! GPU timestamps: a query pool whose ticks are converted to milliseconds.

use std::sync::Arc;

use ash::vk;

use super::{vk_err, Context, Held};
use crate::error::Result;

/// `count` timestamp slots, written by [`super::Recorder::timestamp`].
pub struct Timestamps {
    owned: Arc<QueryPool>,
    pub(crate) pool: vk::QueryPool,
    count: u32,
}

/// The query pool, shared with the recordings that write it.
struct QueryPool {
    ctx: Context,
    raw: vk::QueryPool,
}

impl Drop for QueryPool {
    fn drop(&mut self) {
        // SAFETY: the timestamps and every recording that wrote them are gone, and
        // submissions block until the device is done.
        unsafe { self.ctx.device().destroy_query_pool(self.raw, None) };
    }
}

impl Timestamps {
    /// A query pool of `count` timestamp slots.
    pub fn new(ctx: &Context, count: u32) -> Result<Self> {
        let info = vk::QueryPoolCreateInfo::default()
            .query_type(vk::QueryType::TIMESTAMP)
            .query_count(count);
        // SAFETY: valid device and create info.
        let pool = unsafe { ctx.device().create_query_pool(&info, None) }
            .map_err(vk_err("vkCreateQueryPool"))?;
        Ok(Self {
            owned: Arc::new(QueryPool {
                ctx: ctx.clone(),
                raw: pool,
            }),
            pool,
            count,
        })
    }

    /// A share in the query pool, for a recording that writes it.
    pub(crate) fn held(&self) -> Held {
        self.owned.clone()
    }

    /// Number of timestamp slots.
    pub fn count(&self) -> u32 {
        self.count
    }

    /// All slots in milliseconds since an arbitrary origin (after the work completed).
    pub fn read_ms(&self) -> Result<Vec<f64>> {
        let mut ticks = vec![0u64; self.count as usize];
        // SAFETY: the submission that wrote the queries has completed (blocking submits).
        unsafe {
            self.owned.ctx.device().get_query_pool_results(
                self.pool,
                0,
                &mut ticks,
                vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT,
            )
        }
        .map_err(vk_err("vkGetQueryPoolResults"))?;
        let period_ms = self.owned.ctx.info().timestamp_period_ns as f64 * 1e-6;
        Ok(ticks.iter().map(|&t| t as f64 * period_ms).collect())
    }
}
