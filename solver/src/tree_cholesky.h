// The numeric supernodal Cholesky factorization L L^T = P A P^T on CHOLMOD's analysed structure (its supernodes,
// row indices and layout, so CHOLMOD's own solves read the result), shared by two threads along the elimination
// tree (supernodal_tree.h): the two bins' subtrees are factored at once, and each wide supernode of the top has
// its updates split between the threads by columns and its rows below solved in two halves. Left-looking, with
// the same dense kernels as CHOLMOD's (BLAS syrk and gemm for the updates, LAPACK potrf and BLAS trsm for a
// supernode), each update applied by one thread in a fixed order: the same bits with one thread or two.
#pragma once

#include <memory>
#include <vector>

#include "rounded_solve.h"
#include "sparse_cholesky.h"
#include "supernodal_tree.h"

namespace springblend::internal {

class TreeCholesky {
 public:
  // structure: the analysed factor's indices (its values unused); pattern: A's upper
  // triangle by columns, as analysed. Null where the structure cannot be shared between two threads (no two
  // subtrees worth it, not postordered, or rows not sorted within a supernode): then CHOLMOD factors alone.
  static std::shared_ptr<const TreeCholesky> Plan(const SupernodalFactor& structure, const SymmetricPattern& pattern);

  // Each caller's own buffers.
  struct Workspace {
    std::vector<int> map[2];
    std::vector<double> c[2];
  };

  // L's entries into lx (the factor's xsize doubles, CHOLMOD's layout); f: the planned structure or a copy of it
  // (a clone's factor). False where a diagonal block is not positive definite (lx is then partly written).
  bool Factorize(const SupernodalFactor& f, const double* values, double* lx, Workspace* workspace) const;

  const TreeSplit& split() const { return split_; }

 private:
  struct Update {
    int d, p1, p2;  // supernode d's rows [p1, p2) (positions in its row list) fall in the target's columns
  };
  void Assemble(const SupernodalFactor& f, int s, const double* values, double* lx) const;
  void ApplyUpdates(const SupernodalFactor& f, int s, int c0, int c1, const int* map, double* c, double* lx) const;
  bool Finish(const SupernodalFactor& f, int s, double* lx, bool split_rows) const;
  bool FactorNode(const SupernodalFactor& f, int s, const double* values, double* lx, int* map, double* c) const;

  int n_ = 0, nsuper_ = 0;
  TreeSplit split_;
  std::vector<long> a_start_;   // per supernode: its entries of A in a_dest_ / a_src_
  std::vector<long> a_dest_;    // where in lx
  std::vector<int> a_src_;      // which entry of values
  std::vector<long> u_start_;   // per supernode: the updates it receives, by increasing d
  std::vector<Update> updates_;
  std::vector<char> wide_;      // top supernodes split between the threads
  size_t c_size_ = 1;
};

}  // namespace springblend::internal
