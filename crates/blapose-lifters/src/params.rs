//! Loading tensors by their reference names while counting parameters.
//!
//! The parameter counts of the reference implementations are the check that
//! our architectures are the published ones, so the count must come from
//! the tensors the constructors actually load, not from a formula written
//! next to them. [`ParamLoader`] wraps a `VarBuilder`, keeps PyTorch's
//! distinction between *parameters* (counted by `model.parameters()`) and
//! *buffers* (batch-norm running statistics, not counted), and adds up
//! what was loaded.

use std::cell::Cell;
use std::rc::Rc;

use candle_core::Tensor;
use candle_nn::{Init, VarBuilder};

use crate::error::Result;

/// A `VarBuilder` that counts the parameters it hands out.
#[derive(Clone)]
pub(crate) struct ParamLoader<'a> {
    vb: VarBuilder<'a>,
    count: Rc<Cell<usize>>,
}

impl<'a> ParamLoader<'a> {
    pub(crate) fn new(vb: VarBuilder<'a>) -> Self {
        Self {
            vb,
            count: Rc::new(Cell::new(0)),
        }
    }

    /// The loader for the sub-module `name` (shares the count).
    pub(crate) fn pp(&self, name: impl ToString) -> Self {
        Self {
            vb: self.vb.pp(name),
            count: Rc::clone(&self.count),
        }
    }

    /// A trainable parameter (counted).
    pub(crate) fn param(&self, shape: &[usize], name: &str, init: Init) -> Result<Tensor> {
        let t = self.vb.get_with_hints(shape.to_vec(), name, init)?;
        self.count.set(self.count.get() + t.elem_count());
        Ok(t)
    }

    /// A buffer such as a running statistic (not counted).
    pub(crate) fn buffer(&self, shape: &[usize], name: &str, init: Init) -> Result<Tensor> {
        Ok(self.vb.get_with_hints(shape.to_vec(), name, init)?)
    }

    /// Parameters loaded so far through this loader and all its sub-loaders.
    pub(crate) fn total(&self) -> usize {
        self.count.get()
    }
}
