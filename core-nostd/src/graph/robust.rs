//! Robust models of an edge: how a residual of squared Mahalanobis length `chi2` is weighted.
//!
//! Huber and Cauchy are M-estimators solved by iteratively reweighted least squares: each
//! iteration scales the edge's information by `rho'(chi2)`. A max-mixture (Olson and Agarwal)
//! is a list of Gaussian components that share the edge's measurement and scale its
//! information; each iteration keeps only the most likely component, so the problem stays an
//! ordinary least-squares one. A component with a tiny scale is a "null hypothesis": a wrong
//! loop closure falls to it and stops pulling on the graph.

/// Most components a max-mixture edge can hold.
pub const MAX_MIXTURE_COMPONENTS: usize = 3;

/// One Gaussian component of a max-mixture: weight `w` and information `s * Omega`.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct MixtureComponent {
    /// Prior weight, in `(0, 1]`.
    pub weight: f32,
    /// Scale of the edge's information, `> 0` (`1` for the nominal component).
    pub info_scale: f32,
}

impl MixtureComponent {
    /// The nominal component: weight 1, the edge's own information.
    pub const NOMINAL: MixtureComponent = MixtureComponent {
        weight: 1.0,
        info_scale: 1.0,
    };

    /// `-2 log` of the component's likelihood at `chi2` (up to a constant shared by all
    /// components): `s chi2 - 2 ln w - 3 ln s`.
    #[inline]
    fn cost(&self, chi2: f64) -> f64 {
        let s = self.info_scale as f64;
        s * chi2 - 2.0 * libm::log(self.weight as f64) - 3.0 * libm::log(s)
    }
}

/// The robust model of an edge.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum RobustKernel {
    /// Plain least squares.
    None,
    /// Huber: quadratic up to `sqrt(chi2) = delta`, linear beyond.
    Huber {
        /// Threshold on the Mahalanobis length.
        delta: f64,
    },
    /// Cauchy: `c^2 ln(1 + chi2 / c^2)`.
    Cauchy {
        /// Scale on the Mahalanobis length.
        c: f64,
    },
    /// Max-mixture of up to [`MAX_MIXTURE_COMPONENTS`] components (the first `count` are used).
    MaxMixture {
        /// The components.
        components: [MixtureComponent; MAX_MIXTURE_COMPONENTS],
        /// How many are used (at least 1).
        count: u8,
    },
}

impl RobustKernel {
    /// A two-component max-mixture: the nominal Gaussian and a null hypothesis of weight
    /// `null_weight` with information scaled by `null_scale`.
    pub fn max_mixture_with_null(null_weight: f32, null_scale: f32) -> RobustKernel {
        RobustKernel::MaxMixture {
            components: [
                MixtureComponent::NOMINAL,
                MixtureComponent {
                    weight: null_weight,
                    info_scale: null_scale,
                },
                MixtureComponent::NOMINAL,
            ],
            count: 2,
        }
    }

    /// Like [`RobustKernel::weigh`], but a max-mixture takes its widest component (the
    /// smallest information scale, the null hypothesis) whatever its likelihood; other models
    /// weigh as usual.
    #[inline]
    pub fn weigh_widest(&self, chi2: f64) -> (f64, f64) {
        match *self {
            RobustKernel::MaxMixture { components, count } => {
                let used = (count as usize).clamp(1, MAX_MIXTURE_COMPONENTS);
                let mut widest = components[0];
                for comp in components.iter().take(used) {
                    if comp.info_scale < widest.info_scale {
                        widest = *comp;
                    }
                }
                let c = widest.cost(chi2);
                if c.is_finite() {
                    (widest.info_scale as f64, c)
                } else {
                    (1.0, chi2)
                }
            }
            _ => self.weigh(chi2),
        }
    }

    /// For a residual of squared length `chi2`: the factor that scales the edge's information
    /// in this iteration's normal equations, and the edge's robust cost.
    #[inline]
    pub fn weigh(&self, chi2: f64) -> (f64, f64) {
        match *self {
            RobustKernel::None => (1.0, chi2),
            RobustKernel::Huber { delta } => {
                let d2 = delta * delta;
                if chi2 <= d2 {
                    (1.0, chi2)
                } else {
                    let r = libm::sqrt(chi2);
                    (delta / r, 2.0 * delta * r - d2)
                }
            }
            RobustKernel::Cauchy { c } => {
                let c2 = c * c;
                (1.0 / (1.0 + chi2 / c2), c2 * libm::log1p(chi2 / c2))
            }
            RobustKernel::MaxMixture { components, count } => {
                let used = (count as usize).clamp(1, MAX_MIXTURE_COMPONENTS);
                let mut best = (1.0, f64::INFINITY);
                for comp in components.iter().take(used) {
                    let c = comp.cost(chi2);
                    if c < best.1 {
                        best = (comp.info_scale as f64, c);
                    }
                }
                if best.1.is_finite() {
                    best
                } else {
                    (1.0, chi2)
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn huber_and_cauchy_weights() {
        let h = RobustKernel::Huber { delta: 2.0 };
        assert_eq!(h.weigh(1.0), (1.0, 1.0));
        let (w, c) = h.weigh(16.0);
        assert!((w - 0.5).abs() < 1e-15 && (c - 12.0).abs() < 1e-12);
        let (w, _) = RobustKernel::Cauchy { c: 1.0 }.weigh(3.0);
        assert!((w - 0.25).abs() < 1e-15);
    }

    #[test]
    fn max_mixture_switches_to_null_for_large_errors() {
        let k = RobustKernel::max_mixture_with_null(1e-3, 1e-6);
        assert_eq!(k.weigh(1.0).0, 1.0);
        let (w, c) = k.weigh(1e4);
        assert!((w - 1e-6).abs() < 1e-12);
        assert!(c < 1e4);
    }
}
