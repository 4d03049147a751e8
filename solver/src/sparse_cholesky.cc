#include "sparse_cholesky.h"

#include <cholmod.h>
#include <sys/mman.h>
#include <smumps_c.h>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <Eigen/Sparse>
#include <Eigen/SparseCholesky>
#include <algorithm>
#include <cstdint>
#include <cstring>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "rounded_solve.h"
#include "tree_cholesky.h"
#include "springblend/error.h"

namespace springblend::internal {
namespace {

// The pattern (and values, unless null) as a CHOLMOD matrix, without copying.
cholmod_sparse CholmodView(const SymmetricPattern& pattern, const double* values) {
  cholmod_sparse a{};
  a.nrow = pattern.n;
  a.ncol = pattern.n;
  a.nzmax = pattern.row_indices.size();
  a.p = const_cast<int*>(pattern.column_starts.data());  // NOLINT: read only
  a.i = const_cast<int*>(pattern.row_indices.data());    // NOLINT: read only
  a.x = const_cast<double*>(values);                     // NOLINT: read only
  a.stype = 1;  // upper triangle stored
  a.itype = CHOLMOD_INT;
  a.xtype = values == nullptr ? CHOLMOD_PATTERN : CHOLMOD_REAL;
  a.dtype = CHOLMOD_DOUBLE;
  a.sorted = 1;
  a.packed = 1;
  return a;
}

// A fresh factor's entries (tens of MB, a fresh mapping for every Solver) are first written by its first
// factorization, one 4 KB page fault at a time: asked for huge pages (the kernel's transparent huge pages in
// 'madvise' mode, as on Debian), the same first touch takes a fault per 2 MB. Only the aligned middle of the
// block is advised; a kernel without them ignores the advice, and nothing numerical depends on it.
void AdviseHugePages(void* data, size_t bytes) {
  constexpr uintptr_t kHuge = uintptr_t{2} << 20;
  const uintptr_t first = (reinterpret_cast<uintptr_t>(data) + kHuge - 1) & ~(kHuge - 1);
  const uintptr_t end = (reinterpret_cast<uintptr_t>(data) + bytes) & ~(kHuge - 1);
  if (end > first) madvise(reinterpret_cast<void*>(first), end - first, MADV_HUGEPAGE);
}

// CHOLMOD, supernodal, on the system BLAS (OpenBLAS on Debian).
class CholmodCholesky final : public SparseCholesky {
 public:
  CholmodCholesky(bool rounded_preconditioner, bool tree_factorization)
      : round_(rounded_preconditioner), tree_factorization_(tree_factorization) {
    cholmod_start(&common_);
    common_.supernodal = CHOLMOD_SUPERNODAL;
    common_.quick_return_if_not_posdef = 1;
    common_.print = 0;
    common_.error_handler = nullptr;
  }
  ~CholmodCholesky() override {
    if (factor_ != nullptr) cholmod_free_factor(&factor_, &common_);
    if (solution_ != nullptr) cholmod_free_dense(&solution_, &common_);
    if (work_y_ != nullptr) cholmod_free_dense(&work_y_, &common_);
    if (work_e_ != nullptr) cholmod_free_dense(&work_e_, &common_);
    cholmod_finish(&common_);
  }

  void Analyze(const SymmetricPattern& pattern) override {
    pattern_ = &pattern;
    cholmod_sparse a = View(nullptr);
    if (factor_ != nullptr) cholmod_free_factor(&factor_, &common_);
    factor_ = cholmod_analyze(&a, &common_);
    // Planned on the first preconditioning solve of this factor or of any clone, once for them all: a fresh
    // Solver's clone no longer plans it again (the cat: about 100 ms a Solver), and a factor used only for
    // direct solves (a local finish's) never does.
    schedule_ = std::make_shared<SharedSchedule>();
    tree_.reset();
    if (factor_ == nullptr || common_.status < CHOLMOD_OK) {
      throw Error(ErrorCode::kNumerical,
                  "CHOLMOD could not analyse the Hessian pattern (status " +
                      std::to_string(common_.status) + ")");
    }
    // The numeric factorization shared by two threads along the tree, where it can be (tree_cholesky.h).
    if (tree_factorization_ && factor_->is_super) tree_ = TreeCholesky::Plan(StructureView(), pattern);
    // A solve does 4 lnz flops and is bound by memory; the factorization's dense blocks run on BLAS 3 at
    // about four times the flop rate (cube: 45 ms per factorization, 2.3 ms per solve, fl / 4 lnz = 97).
    solves_per_factorization_ = common_.lnz > 0 ? std::max(1.0, common_.fl / (16.0 * common_.lnz)) : 1.0;
  }

  std::unique_ptr<SparseCholesky> Clone() const override {
    auto copy = std::make_unique<CholmodCholesky>(round_, tree_factorization_);
    copy->pattern_ = pattern_;
    copy->solves_per_factorization_ = solves_per_factorization_;
    copy->schedule_ = schedule_;
    copy->tree_ = tree_;
    // The analysed factor is only read here, so clones may be made concurrently from one rig.
    copy->factor_ = cholmod_copy_factor(factor_, &copy->common_);
    if (copy->factor_ == nullptr) throw Error(ErrorCode::kInternal, "cholmod_copy_factor failed");
    return copy;
  }

  FactorStatus Factorize(const double* values) override {
    rounded_ready_ = false;  // rounded on the first Precondition: a factor used only for direct solves never is
    if (tree_ != nullptr) {
      if (factor_->xtype == CHOLMOD_PATTERN) {
        if (!cholmod_change_factor(CHOLMOD_REAL, 1, 1, 1, 1, factor_, &common_)) return FactorStatus::kFailed;
        AdviseHugePages(factor_->x, factor_->xsize * sizeof(double));  // fresh entries, not yet written
      }
      if (!tree_->Factorize(StructureView(), values, static_cast<double*>(factor_->x), &tree_workspace_)) {
        factor_->minor = 0;
        return FactorStatus::kNotPositiveDefinite;
      }
      factor_->minor = factor_->n;
      return FactorStatus::kOk;
    }
    cholmod_sparse a = View(values);
    const int ok = cholmod_factorize(&a, factor_, &common_);
    if (common_.status == CHOLMOD_NOT_POSDEF ||
        (factor_->minor < factor_->n)) {
      return FactorStatus::kNotPositiveDefinite;
    }
    if (!ok || common_.status < CHOLMOD_OK) return FactorStatus::kFailed;
    return FactorStatus::kOk;
  }

  // The supernodal solve with the factor rounded to single precision (rounded_solve.h).
  void Precondition(const double* b, double* x) override {
    if (!rounded_ready_) RoundFactor();
    if (!rounded_ready_) {
      Solve(b, x);
      return;
    }
    RoundedSupernodalSolve(RoundedView(), &schedule_->plan, b, x, &workspace_);
  }

  void Solve(const double* b, double* x) override {
    const int n = pattern_->n;
    cholmod_dense rhs{};
    rhs.nrow = n;
    rhs.ncol = 1;
    rhs.nzmax = n;
    rhs.d = n;
    rhs.x = const_cast<double*>(b);  // NOLINT: CHOLMOD's C API does not write to B
    rhs.xtype = CHOLMOD_REAL;
    rhs.dtype = CHOLMOD_DOUBLE;
    if (!cholmod_solve2(CHOLMOD_A, factor_, &rhs, nullptr, &solution_, nullptr, &work_y_, &work_e_,
                        &common_)) {
      throw Error(ErrorCode::kNumerical, "CHOLMOD solve failed");
    }
    std::memcpy(x, solution_->x, sizeof(double) * n);
  }

  long FactorNonzeros() const override {
    if (factor_ == nullptr) return 0;
    // Entries of the numeric factor (supernodal: dense blocks, including their explicit zeros).
    return static_cast<long>(factor_->is_super ? factor_->xsize : factor_->nzmax);
  }
  double SolvesPerFactorization() const override { return solves_per_factorization_; }

 private:
  cholmod_sparse View(const double* values) const { return CholmodView(*pattern_, values); }

  // The factor rounded to single precision for Precondition (supernodal factors only), and its workspaces.
  void RoundFactor() {
    if (!round_ || !factor_->is_super || factor_->xtype != CHOLMOD_REAL || factor_->dtype != CHOLMOD_DOUBLE) return;
    const double* values = static_cast<const double*>(factor_->x);
    if (rounded_size_ != factor_->xsize) {
      // Left uninitialised: the rounding below writes every entry, first (a fresh Solver's) on huge pages too.
      rounded_.reset(new float[factor_->xsize]);
      rounded_size_ = factor_->xsize;
      AdviseHugePages(rounded_.get(), rounded_size_ * sizeof(float));
    }
    // Tens of MB streamed once per factorization (the cat: about 6 ms on one thread): shared by the arena's
    // threads, each entry rounded alone, so the copy is the same whatever the split.
    float* rounded = rounded_.get();
    tbb::parallel_for(tbb::blocked_range<size_t>(0, factor_->xsize, size_t{1} << 16),
                      [&](const tbb::blocked_range<size_t>& range) {
                        for (size_t k = range.begin(); k < range.end(); ++k) rounded[k] = static_cast<float>(values[k]);
                      });
    const SupernodalFactor view = RoundedView();
    workspace_.Fit(view, static_cast<int>(factor_->maxesize));
    // How two threads share a solve: from the analysed structure, once for this factor and its clones.
    std::call_once(schedule_->once, [&] { schedule_->plan = PlanSolve(view); });
    rounded_ready_ = true;
  }

  SupernodalFactor RoundedView() const {
    SupernodalFactor view = StructureView();
    view.values = rounded_.get();
    return view;
  }

  SupernodalFactor StructureView() const {
    SupernodalFactor view;
    view.n = pattern_->n;
    view.nsuper = static_cast<int>(factor_->nsuper);
    view.perm = static_cast<const int*>(factor_->Perm);
    view.super = static_cast<const int*>(factor_->super);
    view.pi = static_cast<const int*>(factor_->pi);
    view.px = static_cast<const int*>(factor_->px);
    view.rows = static_cast<const int*>(factor_->s);
    return view;
  }

  // Mutable because lnz is read from it after analysis.
  mutable cholmod_common common_{};
  const SymmetricPattern* pattern_ = nullptr;
  bool round_ = true;
  std::unique_ptr<float[]> rounded_;
  size_t rounded_size_ = 0;
  bool rounded_ready_ = false;  // rounded_ holds the current factor
  SolveWorkspace workspace_;
  // Written once under its flag (by whichever clone preconditions first), then only read.
  struct SharedSchedule {
    std::once_flag once;
    SolveSchedule plan;
  };
  std::shared_ptr<SharedSchedule> schedule_;
  std::shared_ptr<const TreeCholesky> tree_;
  TreeCholesky::Workspace tree_workspace_;
  bool tree_factorization_ = true;
  cholmod_factor* factor_ = nullptr;
  double solves_per_factorization_ = 1.0;
  cholmod_dense* solution_ = nullptr;
  cholmod_dense* work_y_ = nullptr;
  cholmod_dense* work_e_ = nullptr;
};

// MUMPS 5.5 keeps state in Fortran modules (its load-balancing module among them: two factorizations at once
// on two threads fail in SMUMPS_LOAD_INIT), so it is not safe on several threads even with one instance per
// thread; Debian 12 ships 5.5.1. Every call into it takes this lock: the rest of a solve still runs in parallel.
std::mutex& MumpsLock() {
  static std::mutex lock;
  return lock;
}

// MUMPS, multifrontal, in single precision and sequential (Debian's libmumps-seq: a dummy MPI, no OpenMP;
// BLAS 3 on OpenBLAS). Its factor is accurate to about 1e-7 to 1e-4 of a solve's size: a Newton step or a
// preconditioner, never an answer (the convergence test reads the forces in double). The ordering is CHOLMOD's:
// deterministic, so a frame's answer does not depend on the run; a clone reuses it.
// Measured on the face (docs/benchmark.md, "Linear algebra"): no faster than CHOLMOD here. A factorization
// that meets a negative pivot runs to the end (CHOLMOD stops at the first), solves are slower, and calls
// serialize across threads; so CHOLMOD stays the default and this one is there to be measured.
class MumpsSingleCholesky final : public SparseCholesky {
 public:
  MumpsSingleCholesky() {
    id_.comm_fortran = kUseCommWorld;
    id_.par = 1;  // the host works (the only process)
    id_.sym = 1;  // symmetric positive definite: no pivoting, a non-positive pivot is an error
    Call(kInit, "initialise");
    Quiet();
  }
  ~MumpsSingleCholesky() override { Run(kEnd); }
  MumpsSingleCholesky(const MumpsSingleCholesky&) = delete;
  MumpsSingleCholesky& operator=(const MumpsSingleCholesky&) = delete;

  void Analyze(const SymmetricPattern& pattern) override {
    pattern_ = &pattern;
    const size_t entries = pattern.row_indices.size();
    row_.resize(entries);
    column_.resize(entries);
    for (int j = 0; j < pattern.n; ++j) {
      for (int k = pattern.column_starts[j]; k < pattern.column_starts[j + 1]; ++k) {
        row_[k] = pattern.row_indices[k] + 1;  // 1-based coordinates
        column_[k] = j + 1;
      }
    }
    values_.assign(entries, 0.0f);
    rhs_.assign(pattern.n, 0.0f);
    id_.n = pattern.n;
    id_.nnz = static_cast<MUMPS_INT8>(entries);
    id_.irn = row_.data();
    id_.jcn = column_.data();
    id_.a = values_.data();
    if (order_.empty()) order_ = CholmodOrder(pattern);
    Icntl(7) = kGivenOrder;
    id_.perm_in = order_.data();
    Icntl(28) = 1;  // sequential analysis
    Call(kAnalyse, "analyse the Hessian pattern");
    // INFOG(20): the factor's estimated entries (negative: millions); RINFOG(1): the factorization's flops.
    const long estimate = id_.infog[19];
    factor_entries_ = estimate < 0 ? -estimate * 1000000L : estimate;
    const double flops = id_.rinfog[0];
    solves_per_factorization_ = factor_entries_ > 0 ? std::max(1.0, flops / (16.0 * factor_entries_)) : 1.0;
  }

  std::unique_ptr<SparseCholesky> Clone() const override {
    auto copy = std::make_unique<MumpsSingleCholesky>();
    copy->order_ = order_;
    copy->Analyze(*pattern_);
    return copy;
  }

  FactorStatus Factorize(const double* values) override {
    for (size_t k = 0; k < values_.size(); ++k) values_[k] = static_cast<float>(values[k]);
    id_.a = values_.data();
    // Workspace is estimated at analysis; when the numbers need more, allow more and factor again.
    for (int attempt = 0;; ++attempt) {
      const int status = Run(kFactorize);
      // SYM = 1 factors LDL^T without pivoting and does not stop at a non-positive pivot; INFOG(12) counts
      // the negative ones, and a zero pivot is an error (-10).
      if (status >= 0) return id_.infog[11] > 0 ? FactorStatus::kNotPositiveDefinite : FactorStatus::kOk;
      if (status == kNumericallySingular) return FactorStatus::kNotPositiveDefinite;
      if ((status == kWorkspaceTooSmall || status == kIntegerWorkspaceTooSmall) && attempt < 4) {
        Icntl(14) = std::max(Icntl(14), 20) * 2;
        continue;
      }
      return FactorStatus::kFailed;
    }
  }

  void Solve(const double* b, double* x) override {
    const int n = pattern_->n;
    for (int i = 0; i < n; ++i) rhs_[i] = static_cast<float>(b[i]);
    id_.rhs = rhs_.data();
    id_.nrhs = 1;
    id_.lrhs = n;
    Call(kSolve, "solve");
    for (int i = 0; i < n; ++i) x[i] = rhs_[i];
  }

  long FactorNonzeros() const override { return factor_entries_; }
  double SolvesPerFactorization() const override { return solves_per_factorization_; }

 private:
  static constexpr int kUseCommWorld = -987654;
  static constexpr int kInit = -1, kEnd = -2, kAnalyse = 1, kFactorize = 2, kSolve = 3;
  static constexpr int kGivenOrder = 1;
  static constexpr int kNumericallySingular = -10, kWorkspaceTooSmall = -9, kIntegerWorkspaceTooSmall = -8;

  // CHOLMOD's fill-reducing order for the pattern (the better of AMD and METIS by its own count, the same every
  // run) as MUMPS's PERM_IN: position (1-based) of each variable in the pivot order. Both backends then factor
  // in the same order, so they differ only in kernels and precision (MUMPS's own orderings took about as long).
  static std::vector<MUMPS_INT> CholmodOrder(const SymmetricPattern& pattern) {
    cholmod_common common{};
    cholmod_start(&common);
    common.print = 0;
    common.error_handler = nullptr;
    cholmod_sparse a = CholmodView(pattern, nullptr);
    cholmod_factor* factor = cholmod_analyze(&a, &common);
    std::vector<MUMPS_INT> position;
    if (factor != nullptr) {
      const int* perm = static_cast<const int*>(factor->Perm);
      position.assign(pattern.n, 0);
      for (int k = 0; k < pattern.n; ++k) position[perm[k]] = k + 1;
      cholmod_free_factor(&factor, &common);
    }
    cholmod_finish(&common);
    if (position.empty()) throw Error(ErrorCode::kNumerical, "CHOLMOD could not order the Hessian pattern for MUMPS");
    return position;
  }

  // ICNTL(i), 1-based as MUMPS's guide numbers them.
  MUMPS_INT& Icntl(int i) { return id_.icntl[i - 1]; }
  void Quiet() {
    Icntl(1) = -1;  // error messages
    Icntl(2) = -1;  // diagnostics
    Icntl(3) = -1;  // global information
    Icntl(4) = 0;   // no printing at all
  }
  // One call into MUMPS, under the process-wide lock; returns INFOG(1) (negative: an error).
  int Run(int job) {
    id_.job = job;
    const std::lock_guard<std::mutex> hold(MumpsLock());
    smumps_c(&id_);
    return id_.infog[0];
  }
  // Run, throwing on an error.
  void Call(int job, const char* what) {
    if (Run(job) < 0) {
      throw Error(ErrorCode::kNumerical, std::string("MUMPS could not ") + what + " (INFOG(1) " +
                                             std::to_string(id_.infog[0]) + ", INFOG(2) " +
                                             std::to_string(id_.infog[1]) + ")");
    }
  }

  SMUMPS_STRUC_C id_{};
  const SymmetricPattern* pattern_ = nullptr;
  std::vector<MUMPS_INT> row_, column_, order_;
  std::vector<float> values_, rhs_;
  long factor_entries_ = 0;
  double solves_per_factorization_ = 1.0;
};

// Eigen's simplicial LLT: slow on these matrices, kept as an independent reference implementation.
class EigenCholesky final : public SparseCholesky {
 public:
  void Analyze(const SymmetricPattern& pattern) override {
    pattern_ = &pattern;
    std::vector<double> ones(pattern.row_indices.size(), 1.0);
    solver_.analyzePattern(View(ones.data()));
  }
  std::unique_ptr<SparseCholesky> Clone() const override {
    auto copy = std::make_unique<EigenCholesky>();
    copy->Analyze(*pattern_);
    return copy;
  }
  FactorStatus Factorize(const double* values) override {
    solver_.factorize(View(values));
    if (solver_.info() == Eigen::NumericalIssue) return FactorStatus::kNotPositiveDefinite;
    return solver_.info() == Eigen::Success ? FactorStatus::kOk : FactorStatus::kFailed;
  }
  void Solve(const double* b, double* x) override {
    Eigen::Map<const Eigen::VectorXd> rhs(b, pattern_->n);
    Eigen::VectorXd result = solver_.solve(rhs);
    Eigen::Map<Eigen::VectorXd>(x, pattern_->n) = result;
  }
  long FactorNonzeros() const override { return 0; }
  double SolvesPerFactorization() const override { return 20.0; }  // a typical figure; not analysed here

 private:
  using Matrix = Eigen::SparseMatrix<double, Eigen::ColMajor, int>;
  Eigen::Map<const Matrix> View(const double* values) const {
    return Eigen::Map<const Matrix>(pattern_->n, pattern_->n,
                                    static_cast<int>(pattern_->row_indices.size()),
                                    pattern_->column_starts.data(), pattern_->row_indices.data(),
                                    values);
  }
  const SymmetricPattern* pattern_ = nullptr;
  Eigen::SimplicialLLT<Matrix, Eigen::Upper, Eigen::AMDOrdering<int>> solver_;
};

}  // namespace

std::unique_ptr<SparseCholesky> SparseCholesky::Create(LinearSolverType type) {
  switch (type) {
    case LinearSolverType::kCholmodSupernodal:
      return std::make_unique<CholmodCholesky>(true, true);
    case LinearSolverType::kCholmodDouble:
      return std::make_unique<CholmodCholesky>(false, true);
    case LinearSolverType::kCholmodLibrary:
      return std::make_unique<CholmodCholesky>(true, false);
    case LinearSolverType::kEigenSimplicial:
      return std::make_unique<EigenCholesky>();
    case LinearSolverType::kMumpsSingle:
      return std::make_unique<MumpsSingleCholesky>();
  }
  throw Error(ErrorCode::kInternal, "unknown linear solver type");
}

}  // namespace springblend::internal
