//! `/metrics` as `prometheus-client` writes it: every family with its `# HELP` and `# TYPE`,
//! per-scene and per-phase series as labels, OpenMetrics text ending in `# EOF`.
//!
//! The server's counters stay plain atomics on the hot path ([`crate::metrics::Metrics`]: one
//! relaxed add per event); a scrape reads them once into an [`Exposition`], which is a
//! `prometheus-client` [`Collector`] and is encoded by the crate. Counter families are named
//! without `_total` here and the encoder adds it, so every sample keeps the name it had before
//! the crate (`brickcast_edits_applied_total`, ...); only the `# TYPE`/`# HELP` lines name the
//! family as OpenMetrics does (`brickcast_edits_applied`).

use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, MetricEncoder, NoLabelSet};
use prometheus_client::metrics::MetricType;
use prometheus_client::registry::Registry;

/// The content type of [`Exposition::encode`]'s text.
pub const CONTENT_TYPE: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";

/// One series' value.
#[derive(Debug, Clone)]
pub enum Value {
    Counter(u64),
    /// A counter of a fractional amount (seconds).
    Seconds(f64),
    Gauge(i64),
    /// Bucket upper bounds with the observations in each (not cumulative; the last bound is
    /// `f64::MAX`, written `+Inf`), their sum and count.
    Histogram {
        buckets: Vec<(f64, u64)>,
        sum: f64,
        count: u64,
    },
}

impl Value {
    /// A gauge of a count that fits an `i64` (saturating past it: never an encoding error).
    pub fn gauge(n: u64) -> Value {
        Value::Gauge(i64::try_from(n).unwrap_or(i64::MAX))
    }

    fn metric_type(&self) -> MetricType {
        match self {
            Value::Counter(_) | Value::Seconds(_) => MetricType::Counter,
            Value::Gauge(_) => MetricType::Gauge,
            Value::Histogram { .. } => MetricType::Histogram,
        }
    }

    fn encode(&self, encoder: &mut MetricEncoder) -> Result<(), std::fmt::Error> {
        match self {
            Value::Counter(n) => encoder.encode_counter::<NoLabelSet, _, f64>(n, None),
            Value::Seconds(s) => encoder.encode_counter::<NoLabelSet, _, f64>(s, None),
            Value::Gauge(g) => encoder.encode_gauge(g),
            Value::Histogram {
                buckets,
                sum,
                count,
            } => encoder.encode_histogram::<NoLabelSet>(*sum, *count, buckets, None),
        }
    }
}

#[derive(Debug)]
struct Family {
    name: String,
    help: String,
    kind: MetricType,
    /// `(label, value)` pairs of each series (empty: the family's one series) and its value.
    series: Vec<(Vec<(String, String)>, Value)>,
}

/// The families of one scrape, in the order they are added.
#[derive(Debug, Default)]
pub struct Exposition {
    families: Vec<Family>,
}

impl Exposition {
    /// A family of one series. `name` is without the `brickcast_` prefix (and, for counters,
    /// without `_total`).
    pub fn one(&mut self, name: &str, help: &str, value: Value) {
        self.family(name, help, value.metric_type(), [(Vec::new(), value)]);
    }

    /// A family of one series per `label` value, all of `kind`.
    pub fn labelled(
        &mut self,
        name: &str,
        help: &str,
        label: &str,
        rows: impl IntoIterator<Item = (String, Value)>,
    ) {
        let series: Vec<_> = rows
            .into_iter()
            .map(|(key, value)| (vec![(label.to_string(), key)], value))
            .collect();
        let kind = series
            .first()
            .map_or(MetricType::Gauge, |(_, v)| v.metric_type());
        self.family(name, help, kind, series);
    }

    fn family(
        &mut self,
        name: &str,
        help: &str,
        kind: MetricType,
        series: impl IntoIterator<Item = (Vec<(String, String)>, Value)>,
    ) {
        let series: Vec<_> = series.into_iter().collect();
        debug_assert!(
            series
                .iter()
                .all(|(_, v)| std::mem::discriminant(&v.metric_type())
                    == std::mem::discriminant(&kind)),
            "{name}: one type per family"
        );
        self.families.push(Family {
            name: name.to_string(),
            help: help.to_string(),
            kind,
            series,
        });
    }

    /// The OpenMetrics text of every family, `brickcast_`-prefixed, ending in `# EOF`.
    pub fn encode(self) -> String {
        let mut registry = Registry::with_prefix("brickcast");
        registry.register_collector(Box::new(self));
        let mut out = String::new();
        if let Err(e) = prometheus_client::encoding::text::encode(&mut out, &registry) {
            // Only a value the format cannot hold gets here (every gauge saturates first).
            tracing::error!(error = %e, "/metrics could not be encoded");
        }
        out
    }
}

impl Collector for Exposition {
    fn encode(&self, mut encoder: DescriptorEncoder) -> Result<(), std::fmt::Error> {
        for family in &self.families {
            let mut metric =
                encoder.encode_descriptor(&family.name, &family.help, None, family.kind)?;
            for (labels, value) in &family.series {
                if labels.is_empty() {
                    value.encode(&mut metric)?;
                } else {
                    value.encode(&mut metric.encode_family(labels)?)?;
                }
            }
        }
        Ok(())
    }
}
