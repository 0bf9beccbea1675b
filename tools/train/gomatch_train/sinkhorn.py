"""Matching layer (paper sec. 3 "Optimal transport", supp. eq. 9-10): descriptor distances with dustbins,
log-domain Sinkhorn (plus the same iteration in the exp domain, used for training speed) and mutual
nearest-neighbour assignment.

All matrices are (N3 + 1, N2 + 1): rows are 3D points, columns 2D keypoints, the last row/column the dustbin.
Distances, costs and both Sinkhorn solvers also take a batch (B, ...) of equal-size problems (batched training).
"""

import torch

SINKHORN_STOP_THRESHOLD = 1e-6
# exp(-x) for x up to this stays a normal float32 (> 1e-35): the exp-domain solver is exact enough below it.
MAX_EXP_DOMAIN_RANGE = 80.0


def descriptor_distances(desc3d: torch.Tensor, desc2d: torch.Tensor) -> torch.Tensor:
    """Euclidean distances (N3, N2) between descriptors: sqrt(max(|a|^2 + |b|^2 - 2ab, 1e-30))."""
    sq3d = desc3d.pow(2).sum(dim=-1, keepdim=True)
    sq2d = desc2d.pow(2).sum(dim=-1, keepdim=True).transpose(-1, -2)
    if desc3d.dim() == 2:
        squared = torch.addmm(sq2d, desc3d, desc2d.t(), alpha=-2) + sq3d
    else:
        squared = torch.baddbmm(sq2d, desc3d, desc2d.transpose(1, 2), alpha=-2) + sq3d
    return squared.clamp_min(1e-30).sqrt()


def cost_with_dustbins(distances: torch.Tensor, bin_score: torch.Tensor) -> torch.Tensor:
    """Append a dustbin row and column filled with the learnable scalar `bin_score`: (N3+1, N2+1)."""
    *batch, n3d, n2d = distances.shape
    rows = torch.cat([distances, bin_score.expand(*batch, n3d, 1)], dim=-1)
    return torch.cat([rows, bin_score.expand(*batch, 1, n2d + 1)], dim=-2)


def marginals(n3d: int, n2d: int, like: torch.Tensor):
    """Row marginals [1]*N3 + [N2] and column marginals [1]*N2 + [N3], both divided by N3 + N2."""
    one = like.new_ones(1)
    mu = torch.cat([one.expand(n3d), one * n2d]) / (n3d + n2d)
    nu = torch.cat([one.expand(n2d), one * n3d]) / (n3d + n2d)
    return mu, nu


def log_sinkhorn(cost: torch.Tensor, mu: torch.Tensor, nu: torch.Tensor, eps: float, max_iters: int):
    """Entropy-regularised optimal transport in the log domain.

    With M(u, v)_ij = (-C_ij + u_i + v_j) / eps, alternates
        u <- eps * (log(mu + 1e-8) - logsumexp_j M(u, v)) + u
        v <- eps * (log(nu + 1e-8) - logsumexp_i M(u, v)) + v
    for at most `max_iters` iterations, stopping early once ||u - u_prev||_2 < 1e-6 (in every problem of a batch).
    Returns (log P, iterations run) with log P = M(u, v), the log of the transport plan.
    """

    def modified_cost(u, v):
        return (-cost + u.unsqueeze(-1) + v.unsqueeze(-2)) / eps

    u, v = torch.zeros_like(mu), torch.zeros_like(nu)
    log_mu, log_nu = torch.log(mu + 1e-8), torch.log(nu + 1e-8)
    iterations = 0
    for _ in range(max_iters):
        u_prev = u
        u = eps * (log_mu - torch.logsumexp(modified_cost(u, v), dim=-1)) + u
        v = eps * (log_nu - torch.logsumexp(modified_cost(u, v).transpose(-2, -1), dim=-1)) + v
        iterations += 1
        if (u - u_prev).norm(dim=-1).max() < SINKHORN_STOP_THRESHOLD:
            break
    return modified_cost(u, v), iterations


def scaling_sinkhorn(cost: torch.Tensor, mu: torch.Tensor, nu: torch.Tensor, eps: float, max_iters: int):
    """The iteration of `log_sinkhorn`, carried out with scaling vectors (same result up to float rounding).

    With s = min C, K = exp(-(C - s) / eps), a = exp((u - s) / eps), b = exp(v / eps) the log-domain updates read
    a <- (mu + 1e-8) / (K b), b <- (nu + 1e-8) / (K^T a), and log P = log a_i + log K_ij + log b_j; the stop test
    eps * ||log a - log a_prev|| < 1e-6 is the log-domain one. Two matrix-vector products per iteration instead of
    two logsumexp passes; the iterations run without autograd and `ScalingSinkhornPlan` differentiates them
    (the scaling vectors of every iteration kept, not the matrices). Used for training.
    Requires (max C - min C) / eps <= MAX_EXP_DOMAIN_RANGE so that K has no underflow (s is per problem).
    """
    row_mass, col_mass = mu + 1e-8, nu + 1e-8
    with torch.no_grad():
        shift = cost.amin(dim=(-2, -1), keepdim=True)
        k = ((cost - shift) / -eps).exp()
        batch = cost.shape[:-2]
        b = nu.new_ones(batch + nu.shape[-1:])
        log_a_prev = (shift.squeeze(-1) / -eps).expand(batch + mu.shape[-1:])
        rows, columns = [], [b]
        for _ in range(max_iters):
            a = row_mass / matvec(k, b)
            b = col_mass / matvec(k.transpose(-2, -1), a)
            rows.append(a)
            columns.append(b)
            log_a = a.log()
            if (eps * (log_a - log_a_prev)).norm(dim=-1).max() < SINKHORN_STOP_THRESHOLD:
                break
            log_a_prev = log_a
    log_plan = ScalingSinkhornPlan.apply(cost, k, shift, torch.stack(rows), torch.stack(columns), row_mass, col_mass,
                                         eps)  # fmt: skip
    return log_plan, len(rows)


class ScalingSinkhornPlan(torch.autograd.Function):
    """log P = log a_T + log K + log b_T from the scaling vectors a_1..a_T, b_0..b_T of `scaling_sinkhorn`, with
    the gradient of the unrolled iteration computed in reverse from those vectors alone.

    With x_t = log a_t = log r - log(K b_{t-1}) and y_t = log b_t = log c - log(K^T a_t), the adjoints run
        w_t = ybar_t b_t / c,  xbar_t = [t = T] sum_j G_ij - a_t (K w_t),  z_t = xbar_t a_t / r,
        ybar_{t-1} = -b_{t-1} (K^T z_t),   from ybar_T = sum_i G_ij,
    and dL/dK = -sum_t (a_t w_t^T + z_t b_{t-1}^T), one product of two (R, 2T) and (2T, C) factors instead of 2T
    outer products; dL/dC = -(G + K * dL/dK) / eps. Autograd through the loop would keep a matrix per iteration.
    """

    @staticmethod
    def forward(ctx, cost, k, shift, rows, columns, row_mass, col_mass, eps):
        ctx.save_for_backward(k, rows, columns, row_mass, col_mass)
        ctx.eps = eps
        return rows[-1].log().unsqueeze(-1) + (cost - shift) / -eps + columns[-1].log().unsqueeze(-2)

    @staticmethod
    def backward(ctx, grad):
        k, rows, columns, row_mass, col_mass = ctx.saved_tensors
        steps = len(rows)
        row_grad = grad.sum(dim=-1)
        col_grad = grad.sum(dim=-2)
        left, right = [], []
        for t in range(steps, 0, -1):
            a, b, b_prev = rows[t - 1], columns[t], columns[t - 1]
            w = col_grad * b / col_mass
            x_bar = (row_grad if t == steps else 0.0) - a * matvec(k, w)
            z = x_bar * a / row_mass
            col_grad = -b_prev * matvec(k.transpose(-2, -1), z)
            left += [a, z]
            right += [w, b_prev]
        k_grad = torch.matmul(torch.stack(left, dim=-1), torch.stack(right, dim=-2))
        cost_grad = (grad - k * k_grad) / -ctx.eps
        return cost_grad, None, None, None, None, None, None, None


def matvec(matrix: torch.Tensor, vector: torch.Tensor) -> torch.Tensor:
    """matrix @ vector for one (R, C) matrix and (C,) vector or a batch (B, R, C), (B, C)."""
    return (matrix @ vector.unsqueeze(-1)).squeeze(-1)


def largest_spread(cost: torch.Tensor) -> torch.Tensor:
    """max C - min C, the largest over the problems of a batch."""
    detached = cost.detach()
    return (detached.amax(dim=(-2, -1)) - detached.amin(dim=(-2, -1))).max()


def transport(cost: torch.Tensor, mu: torch.Tensor, nu: torch.Tensor, eps: float, max_iters: int):
    """(log P, iterations): the reference's log-domain arithmetic for inference (no autograd), the equivalent
    exp-domain iteration when gradients are recorded and the cost range allows it (training speed)."""
    if torch.is_grad_enabled() and float(largest_spread(cost)) / eps <= MAX_EXP_DOMAIN_RANGE:
        return scaling_sinkhorn(cost, mu, nu, eps, max_iters)
    return log_sinkhorn(cost, mu, nu, eps, max_iters)


@torch.no_grad()
def mutual_assignment(plan: torch.Tensor):
    """Matches (i3d, i2d) from the plan without dustbins, sorted by 3D index then 2D index.

    A match is a mutual nearest neighbour (argmax of its row and of its column). When there are at most 4
    mutual matches, all distinct one-way nearest-neighbour pairs of both directions are returned instead.
    """
    scores = plan[:-1, :-1]
    n3d, n2d = scores.shape
    best2d = scores.argmax(dim=1)
    best3d = scores.argmax(dim=0)
    rows = torch.arange(n3d, device=plan.device)
    mutual = best3d[best2d] == rows
    i3d, i2d = rows[mutual], best2d[mutual]
    if i3d.numel() <= 4:
        cols = torch.arange(n2d, device=plan.device)
        keys = torch.unique(torch.cat([rows * n2d + best2d, best3d * n2d + cols]), sorted=True)
        i3d, i2d = keys // n2d, keys % n2d
    return i3d, i2d
